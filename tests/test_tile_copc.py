"""A catalog tiled as COPC (``--copc``): every tile streamable, enrichment keeps it COPC and
computes what it computes on LAZ tiles, and a served tile answers bounds queries over HTTP."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import copclib
import laspy
import numpy as np
import pandas as pd
import pytest

from standgrid.catalog import Catalog, TilingSettings
from standgrid.errors import TilingError
from standgrid.export.las import read_tile
from standgrid.tiling.setup import settle_tiling
from tests.pipeline_fixtures import BUFFER_M, copc_pair, enriched_pair


@pytest.fixture(scope="module")
def copc_catalog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The bundled pair tiled as COPC (2 m buffer), enriched and compared (shared)."""
    return copc_pair(tmp_path_factory)


@pytest.fixture(scope="module")
def laz_catalog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same missions and options, LAZ tiles (the shared catalog)."""
    return enriched_pair(tmp_path_factory).path


def _tiles(root: Path) -> dict[str, Path]:
    catalog = Catalog.open(root)
    return {rel: root / rel for epoch in catalog.epochs for rel in catalog.tiles(epoch)}


def test_every_tile_is_a_valid_copc_file_after_enrichment(copc_catalog: Path) -> None:
    tiles = _tiles(copc_catalog)
    assert tiles and all(rel.endswith(".copc.laz") for rel in tiles)
    for path in tiles.values():
        reader = copclib.FileReader(str(path))  # a second reader: copclib's own checks
        try:
            assert reader.ValidateSpatialBounds(False)
            in_nodes = sum(n.point_count for n in reader.GetAllNodes())
        finally:
            reader.Close()
        with laspy.CopcReader.open(path) as copc:
            assert len(copc.query()) == copc.header.point_count == in_nodes
            names = set(copc.header.point_format.extra_dimension_names)
        assert {"height_above_ground", "tree_id"} <= names  # enrichment's fields are in
    state = json.loads((copc_catalog / "catalog.json").read_text())
    assert state["tiling"] == {"buffer": BUFFER_M, "laz": True, "copc": True}
    for epoch in state["epochs"]:
        vpc = json.loads((copc_catalog / f"tiles_{epoch}.vpc").read_text())
        assets = [f["assets"]["data"] for f in vpc["features"]]
        assert all(a["href"].endswith(".copc.laz") for a in assets)
        assert {a["type"] for a in assets} == {"application/vnd.laszip+copc"}


def _sorted_cloud(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    cloud = read_tile(path, include_withheld=True)
    order = np.lexsort(cloud.xyz.T[::-1])
    return cloud.xyz[order], {name: values[order] for name, values in cloud.fields.items()}


def test_copc_and_laz_catalogs_hold_the_same_points_fields_and_metrics(
    copc_catalog: Path, laz_catalog: Path
) -> None:
    copc_tiles, laz_tiles = _tiles(copc_catalog), _tiles(laz_catalog)
    assert sorted(r.removesuffix(".copc.laz") for r in copc_tiles) == sorted(
        r.removesuffix(".laz") for r in laz_tiles
    )
    for rel, path in copc_tiles.items():
        xyz, fields = _sorted_cloud(path)
        want_xyz, want = _sorted_cloud(laz_tiles[rel.removesuffix(".copc.laz") + ".laz"])
        np.testing.assert_array_equal(xyz, want_xyz)
        assert fields.keys() == want.keys()
        for name, values in want.items():  # ground, heights, tree ids: point order is moot
            np.testing.assert_array_equal(fields[name], values, err_msg=f"{rel} {name}")
    got = pd.read_parquet(copc_catalog / "tables" / "stand_metrics.parquet")
    want_metrics = pd.read_parquet(laz_catalog / "tables" / "stand_metrics.parquet")
    # sums over points in another order: equal to round-off
    pd.testing.assert_frame_equal(got, want_metrics, check_exact=False, rtol=1e-9, atol=1e-12)
    for epoch in Catalog.open(copc_catalog).epochs:
        name = f"tree_list_{epoch}.parquet"
        pd.testing.assert_frame_equal(
            pd.read_parquet(copc_catalog / "tables" / name),
            pd.read_parquet(laz_catalog / "tables" / name),
            check_exact=False,
            rtol=1e-9,
            atol=1e-12,
        )


@pytest.fixture(scope="module")
def served(copc_catalog: Path) -> Iterator[str]:
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    with running(create_app(copc_catalog)) as server:
        assert server.base_url is not None
        yield server.base_url


def test_a_served_catalog_tile_answers_a_bounds_query_over_http(
    copc_catalog: Path, served: str
) -> None:
    rel, path = max(_tiles(copc_catalog).items(), key=lambda item: item[1].stat().st_size)
    local = laspy.read(path)
    lo = np.array([np.quantile(local.x, 0.3), np.quantile(local.y, 0.3)])
    hi = np.array([np.quantile(local.x, 0.7), np.quantile(local.y, 0.7)])
    # laspy compares stored integers against the bounds rounded to the 1 mm lattice
    scale, offset = local.header.scales[:2], local.header.offsets[:2]
    lo_i, hi_i = np.round((lo - offset) / scale), np.round((hi - offset) / scale)
    stored = np.column_stack([local.X, local.Y])
    inside = np.all((stored >= lo_i) & (stored <= hi_i), axis=1)
    assert 0 < inside.sum() < len(local)
    with laspy.CopcReader.open(f"{served}/files/{rel}") as reader:
        got = reader.query(laspy.copc.Bounds(mins=lo, maxs=hi))

    def rows(points: laspy.ScaleAwarePointRecord) -> np.ndarray:
        table = np.column_stack(
            [points.X, points.Y, points.Z, points["tree_id"], points.classification]
        ).astype(np.int64)
        return table[np.lexsort(table.T[::-1])]

    np.testing.assert_array_equal(rows(got), rows(local.points[inside]))


def test_the_viewer_is_told_to_stream_and_the_server_reads_copc_cells_too(
    copc_catalog: Path, served: str
) -> None:
    import httpx
    import pyogrio

    config = httpx.get(f"{served}/viewer/config.json").json()
    assert config["tiles"] == "copc" and {e["tiles"] for e in config["epochs"]} == {"copc"}
    cells = pyogrio.read_dataframe(copc_catalog / "index.gpkg", layer="cells")
    row = cells.sort_values("point_count").iloc[-1]
    answer = httpx.get(f"{served}/viewer/points/{row['epoch']}/{row['cell_id']}")
    assert answer.status_code == 200
    length = int.from_bytes(answer.content[:4], "little")
    header = json.loads(answer.content[4 : 4 + length])
    las = laspy.read(copc_catalog / row["tile_path"])
    core = int((~np.asarray(las.withheld, dtype=bool)).sum())
    assert header["count"] == core == int(row["point_count"])
    assert header["meta"]["tile"] == f"files/{row['tile_path']}"


def test_tiling_settings_keep_the_catalogs_format_unless_told(tmp_path: Path) -> None:
    grid = {"crs": "EPSG:32632", "cell_size": 20.0, "origin": [0.0, 0.0], "levels": 2}
    catalog = Catalog.create(tmp_path / "c", grid, "EPSG:32632")
    with catalog.transaction() as txn:
        assert settle_tiling(txn, None, None) == TilingSettings(0.0, True, False)
        assert settle_tiling(txn, 2.0, None, True) == TilingSettings(2.0, True, True)
        assert settle_tiling(txn, None, None) == TilingSettings(2.0, True, True)  # kept
        assert settle_tiling(txn, None, False) == TilingSettings(2.0, False, False)  # LAS
        with pytest.raises(TilingError, match="COPC"):
            settle_tiling(txn, None, False, True)
