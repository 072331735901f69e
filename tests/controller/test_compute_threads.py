"""The session's compute threads: torch's and numpy's BLAS set together, process-wide."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from threadpoolctl import threadpool_info, threadpool_limits

import controller.perception.learned as learned
from controller.perception.learned import limit_compute_threads


@pytest.fixture
def restored_threads():
    """The limits this test sets are undone afterwards (they are process-wide)."""
    torch_threads = torch.get_num_threads()
    with threadpool_limits(limits=None):  # restores the BLAS threads on exit
        yield
    torch.set_num_threads(torch_threads)


def blas_threads() -> set[int]:
    np.ones(1)  # numpy's BLAS is loaded with numpy
    return {pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"}


def test_both_libraries_get_the_threads_asked(restored_threads) -> None:
    assert limit_compute_threads(1) == 1
    assert torch.get_num_threads() == 1
    assert blas_threads() == {1}


@pytest.mark.parametrize(("cores", "expected"), [(1, 1), (2, 1), (3, 1), (8, 4), (64, 4)])
def test_automatic_is_half_the_cores_at_most_four(
    restored_threads, monkeypatch, cores: int, expected: int
) -> None:
    monkeypatch.setattr(learned.os, "cpu_count", lambda: cores)
    assert limit_compute_threads(0) == expected
    assert torch.get_num_threads() == expected


def test_negative_threads_are_refused() -> None:
    with pytest.raises(ValueError, match="compute threads"):
        limit_compute_threads(-1)
