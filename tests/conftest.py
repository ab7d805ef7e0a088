"""Shared fixtures: the real data folder (../shared/data), skipped cleanly when absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("STANDGRID_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))
REAL = SHARED_DATA / "real"
BUNDLED_MISSIONS = REPO_ROOT / "data" / "missions"


def real_file(relative: str) -> Path:
    """A file under ../shared/data/real, or skip the test when it is not there."""
    path = REAL / relative
    if not path.exists():
        pytest.skip(f"real data not available: {path}")
    return path


@pytest.fixture
def vilens() -> Path:
    """The real VILENS samples folder."""
    return real_file("vilens")


@pytest.fixture
def als() -> Path:
    """The real airborne laser scans folder."""
    return real_file("als")
