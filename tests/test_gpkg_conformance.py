"""The catalog's GeoPackage is a conformant GeoPackage 1.2 that GDAL opens without warnings."""

from __future__ import annotations

import shutil
import sqlite3
import subprocess
from pathlib import Path

import pytest

from standgrid.pipeline.tile import tile_missions
from standgrid.tiling.options import TileOptions
from tests.conftest import BUNDLED_MISSIONS

VALIDATOR = Path("/usr/share/doc/python3-gdal/examples/validate_gpkg.py")


@pytest.fixture(scope="module")
def index(tmp_path_factory: pytest.TempPathFactory) -> Path:
    mission = sorted(BUNDLED_MISSIONS.iterdir())[0]
    catalog = tmp_path_factory.mktemp("conformance") / "catalog"
    tile_missions([mission], catalog, TileOptions())
    return catalog / "index.gpkg"


def test_index_is_geopackage_1_2(index: Path) -> None:
    with sqlite3.connect(index) as db:
        application_id = db.execute("PRAGMA application_id").fetchone()[0]
        user_version = db.execute("PRAGMA user_version").fetchone()[0]
        styles = db.execute(
            "SELECT data_type FROM gpkg_contents WHERE table_name = 'layer_styles'"
        ).fetchone()
    assert application_id.to_bytes(4, "big") == b"GPKG"
    assert user_version == 10200
    assert styles == ("attributes",)


@pytest.mark.skipif(
    not (VALIDATOR.exists() and shutil.which("ogrinfo")),
    reason="GDAL's validate_gpkg.py / ogrinfo not installed (Debian: python3-gdal gdal-bin)",
)
def test_gdal_validates_and_opens_the_index_without_warnings(index: Path) -> None:
    check = subprocess.run(
        ["/usr/bin/python3", str(VALIDATOR), str(index)], capture_output=True, text=True
    )
    assert check.returncode == 0, check.stdout + check.stderr
    info = subprocess.run(
        ["ogrinfo", "-so", "-al", str(index)], capture_output=True, text=True, check=True
    )
    assert "Warning" not in info.stderr and "ERROR" not in info.stderr, info.stderr
