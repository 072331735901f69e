"""Shared pytest setup: `slow` and `hardware` tests are skipped unless asked for, and every test
starts with the process's own compute threads."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from threadpoolctl import threadpool_limits


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--run-slow", action="store_true", help="also run tests marked slow")
    parser.addoption("--run-hardware", action="store_true", help="also run tests marked hardware")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for marker, option in (("slow", "--run-slow"), ("hardware", "--run-hardware")):
        if config.getoption(option):
            continue
        skip = pytest.mark.skip(reason=f"{marker} test: pass {option} to run")
        for item in items:
            if marker in item.keywords:
                item.add_marker(skip)


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded generator: tests never draw from global random state."""
    return np.random.default_rng(1234)


@pytest.fixture(autouse=True)
def process_compute_threads():
    """A service's perception sets the process's torch and BLAS threads
    (``limit_compute_threads``); they are put back after each test, so no test runs on what an
    earlier one left."""
    threads = torch.get_num_threads()
    with threadpool_limits(limits=None):  # puts the BLAS threads back on exit
        yield
    torch.set_num_threads(threads)
