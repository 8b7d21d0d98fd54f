"""Shared pytest fixtures (keep minimal: each fixture here is used by several test files)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent


def pytest_configure(config: pytest.Config) -> None:
    """One thread each for BLAS and OpenCV in a pytest-xdist worker: the workers already use every
    core, and thread pools of their own on top oversubscribe them (OpenBLAS's threads spin while
    they wait). On 2 cores the suite took 600 s with two workers as they were, 462 s held to one
    thread each, and 877 s in one process (2026-11-29)."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import cv2
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
        cv2.setNumThreads(1)


@pytest.fixture
def rng() -> np.random.Generator:
    """A fixed-seed generator, fresh for every test."""
    return np.random.default_rng(12345)


@pytest.fixture
def demo_map_path() -> Path:
    """The shipped demo map (maps/demo.csv)."""
    return REPO / "maps" / "demo.csv"
