"""The session's compute threads: torch's and numpy's BLAS set together, process-wide (put
back after each test by the conftest)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from threadpoolctl import threadpool_info

import controller.perception.learned as learned
from controller.perception.learned import limit_compute_threads


def blas_threads() -> set[int]:
    np.ones(1)  # numpy's BLAS is loaded with numpy
    return {pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"}


def test_both_libraries_get_the_threads_asked() -> None:
    assert limit_compute_threads(1) == 1
    assert torch.get_num_threads() == 1
    assert blas_threads() == {1}


@pytest.mark.parametrize(("cores", "expected"), [(1, 1), (2, 1), (3, 1), (8, 4), (64, 4)])
def test_automatic_is_half_the_cores_at_most_four(monkeypatch, cores: int, expected: int) -> None:
    monkeypatch.setattr(learned.os, "cpu_count", lambda: cores)
    assert limit_compute_threads(0) == expected
    assert torch.get_num_threads() == expected


def test_negative_threads_are_refused() -> None:
    with pytest.raises(ValueError, match="compute threads"):
        limit_compute_threads(-1)
