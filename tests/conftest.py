"""Shared fixtures: the real data folder (../shared/data), skipped cleanly when absent."""

from __future__ import annotations

import os
from collections.abc import Iterator
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


@pytest.fixture(scope="module")
def enriched_catalog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The bundled pair tiled, enriched and compared (made once per session)."""
    from tests.pipeline_fixtures import enriched_pair

    return enriched_pair(tmp_path_factory).path


@pytest.fixture(scope="module")
def enriched_base(enriched_catalog: Path) -> Iterator[str]:
    """A real uvicorn server (in a thread) on :func:`enriched_catalog`: its base URL."""
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    with running(create_app(enriched_catalog)) as server:
        assert server.base_url is not None
        yield server.base_url
