"""Shared pytest fixtures (keep minimal: each fixture here is used by several test files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture
def rng() -> np.random.Generator:
    """A fixed-seed generator, fresh for every test."""
    return np.random.default_rng(12345)


@pytest.fixture
def demo_map_path() -> Path:
    """The shipped demo map (maps/demo.csv)."""
    return REPO / "maps" / "demo.csv"
