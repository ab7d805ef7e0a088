"""The catalog's GeoPackage index as one object: a layer replaced whole keeps no old row."""

from __future__ import annotations

from pathlib import Path

import geopandas as gpd
import pyogrio
import shapely

from standgrid.catalog import Catalog
from standgrid.catalog.index import CatalogIndex

GRID = {"crs": "EPSG:32632", "cell_size": 20.0, "origin": [500000.0, 6000000.0], "levels": 3}


def _layer(pairs: list[str]) -> gpd.GeoDataFrame:
    points = [shapely.Point(500000.0 + k, 6000000.0) for k in range(len(pairs))]
    return gpd.GeoDataFrame({"pair": pairs}, geometry=points, crs="EPSG:32632")


def test_replace_all_drops_every_old_row_and_keeps_other_layers(tmp_path: Path) -> None:
    catalog = Catalog.create(tmp_path / "cat", GRID, "EPSG:32632", "grid")
    with catalog.transaction() as txn:
        index = CatalogIndex(catalog, txn)
        index.replace_all("changes", _layer(["a-b", "a-b"]))
        index.replace_all("other", _layer(["kept"]))
        index.save()
    with catalog.transaction() as txn:
        index = CatalogIndex(catalog, txn)
        index.replace_all("changes", _layer(["b-c"]), style="<qgis></qgis>")
        assert list(index.read("changes")["pair"]) == ["b-c"]  # read back as replaced
        index.save()
    gpkg = catalog.path("index.gpkg")
    assert list(pyogrio.read_dataframe(gpkg, layer="changes")["pair"]) == ["b-c"]
    assert list(pyogrio.read_dataframe(gpkg, layer="other")["pair"]) == ["kept"]
