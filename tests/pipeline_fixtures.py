"""Shared, session-cached catalogs for the pipeline acceptance tests.

The bundled simulated pair (``data/missions``, truth in ``data/truth``) is tiled, enriched
and compared ONCE per test session (about 30 s) by :func:`enriched_pair`; every test reads
that catalog and must not modify it (copy it with :func:`copy_catalog` to change it). The
cache is module-level, not a pytest fixture, so test modules that each wrap it in their own
session fixture still share one run.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from tests.conftest import BUNDLED_MISSIONS, REPO_ROOT

TRUTH_ROOT = REPO_ROOT / "data" / "truth"
CRS = "EPSG:32630"
#: epoch -> mission folder name of the bundled pair.
MISSIONS = {
    "2024": "2024-05-14-wytham-anymal-coyote",
    "2028": "2028-05-20-wytham-frontier-v15",
}
#: The simulated stand (data/README.md): trees exist only inside it.
STAND_BOUNDS = (614700.0, 5737110.0, 614780.0, 5737190.0)
#: Tile buffer of the shared catalog (withheld points must survive enrichment).
BUFFER_M = 2.0

_cache: dict[str, Any] = {}


@dataclass(frozen=True)
class EnrichedPair:
    """The shared catalog and the report of the run that made it."""

    path: Path
    report: dict[str, Any]


def enriched_pair(factory: pytest.TempPathFactory) -> EnrichedPair:
    """Both bundled missions tiled (20 m grid, 2 m buffer), enriched and compared, once."""
    if "pair" not in _cache:
        from standgrid.pipeline.run import run_pipeline
        from standgrid.tiling.options import TileOptions

        folder = factory.mktemp("shared") / "catalog"
        report = run_pipeline([BUNDLED_MISSIONS], folder, TileOptions(buffer=BUFFER_M))
        _cache["pair"] = EnrichedPair(folder, report.to_dict())
    pair: EnrichedPair = _cache["pair"]
    return pair


def copc_pair(factory: pytest.TempPathFactory) -> Path:
    """Both bundled missions tiled as COPC (20 m grid, 2 m buffer), enriched and compared,
    once (the same options as :func:`enriched_pair` but ``copc=True``)."""
    if "copc" not in _cache:
        from standgrid.pipeline.run import run_pipeline
        from standgrid.tiling.options import TileOptions

        folder = factory.mktemp("copc") / "catalog"
        run_pipeline([BUNDLED_MISSIONS], folder, TileOptions(buffer=BUFFER_M, copc=True))
        _cache["copc"] = folder
    path: Path = _cache["copc"]
    return path


def tiled_grid25(factory: pytest.TempPathFactory) -> Path:
    """Both bundled missions tiled on a 25 m grid, not enriched (a few seconds), once."""
    if "grid25" not in _cache:
        from standgrid.pipeline.tile import tile_missions
        from standgrid.tiling.options import TileOptions

        folder = factory.mktemp("grid25") / "catalog"
        tile_missions(
            [BUNDLED_MISSIONS / m for m in MISSIONS.values()], folder, TileOptions(cell_size=25.0)
        )
        _cache["grid25"] = folder
    path: Path = _cache["grid25"]
    return path


def copy_catalog(source: Path, target: Path) -> Path:
    """A private copy of a catalog a test may change."""
    shutil.copytree(source, target)
    return target


# --- ground truth ------------------------------------------------------------------------


def truth_folder(epoch: str) -> Path:
    return TRUTH_ROOT / MISSIONS[epoch]


def truth_trees(epoch: str) -> pd.DataFrame:
    """The simulator's trees of one epoch (``status`` alive / harvested / new)."""
    return pd.read_csv(truth_folder(epoch) / "trees.csv")


def standing_truth_trees(epoch: str) -> pd.DataFrame:
    """Trees standing at the epoch's scan (harvested ones are absent from its scans)."""
    trees = truth_trees(epoch)
    return trees[trees["status"] != "harvested"].reset_index(drop=True)


def match_one_to_one(
    xy_a: np.ndarray, xy_b: np.ndarray, max_distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``a`` and ``b`` paired one to one, minimising total distance within the limit."""
    from scipy.optimize import linear_sum_assignment

    if len(xy_a) == 0 or len(xy_b) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    d = np.hypot(xy_a[:, None, 0] - xy_b[None, :, 0], xy_a[:, None, 1] - xy_b[None, :, 1])
    cost = np.where(d <= max_distance, d, 1e9)
    rows, cols = linear_sum_assignment(cost)
    ok = cost[rows, cols] <= max_distance
    return rows[ok], cols[ok]


# --- a tiny hand-built catalog -----------------------------------------------------------

SMALL_ORIGIN = (600000.0, 5720000.0)  # corner of cell A
#: (ix, iy) offsets of the cells from cell A, per epoch. C is 80 m from B (far beyond the
#: 10 m halo) and holds two points only, so ground filtering finds no ground in its block.
SMALL_CELLS = {
    "2024": {"A": (0, 0), "B": (1, 0), "C": (5, 0)},
    "2028": {"A": (0, 0), "D": (0, 1)},
}
SMALL_DATES = {"2024": "2024-05-14", "2028": "2028-05-20"}


def _ground_and_tree(rng: np.random.Generator, xmin: float, ymin: float) -> np.ndarray:
    """A 20 m cell of sloping ground (4 pts/m2) with one 15 m cone tree in the middle."""
    gx, gy = np.meshgrid(np.arange(0.25, 20.0, 0.5), np.arange(0.25, 20.0, 0.5))
    gx, gy = gx.ravel() + xmin, gy.ravel() + ymin

    def ground(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return 100.0 + 0.05 * (x - SMALL_ORIGIN[0]) + 0.02 * (y - SMALL_ORIGIN[1])

    gz = ground(gx, gy) + rng.normal(0, 0.01, len(gx))
    n = 600
    h = rng.uniform(5.0, 15.0, n)  # cone: radius shrinks from 2.5 m at 5 m to 0 at 15 m
    r = 2.5 * (15.0 - h) / 10.0
    a = rng.uniform(0, 2 * np.pi, n)
    tx, ty = xmin + 10.0 + r * np.cos(a), ymin + 10.0 + r * np.sin(a)
    tz = ground(np.full(n, xmin + 10.0), np.full(n, ymin + 10.0)) + h
    return np.column_stack(
        [np.concatenate([gx, tx]), np.concatenate([gy, ty]), np.concatenate([gz, tz])]
    )


def build_small_catalog(root: Path) -> Path:
    """Two epochs on a 20 m grid, written with the export API (no georeferencing involved).

    2024: cells A, B (ground + one tree) and C (two points 20 m up, isolated: no ground);
    2028: cells A and D. So in a comparison B and C are ``from_only``, D is ``to_only``.
    """
    from standgrid.catalog import Catalog
    from standgrid.export.gpkg import cell_row, write_index
    from standgrid.export.las import write_tile
    from standgrid.partition import StandGrid
    from standgrid.pointcloud import PointCloud

    grid = StandGrid(CRS, 20.0)
    catalog = Catalog.create(root, grid.to_dict(), CRS, "grid")
    rng = np.random.default_rng(11)
    rows = []
    with catalog.transaction() as txn:
        for number, (epoch, cells) in enumerate(sorted(SMALL_CELLS.items()), start=1):
            mission = f"{SMALL_DATES[epoch]}-test-robot-r{number}"
            rels = []
            for name, (dx, dy) in cells.items():
                xmin, ymin = SMALL_ORIGIN[0] + 20.0 * dx, SMALL_ORIGIN[1] + 20.0 * dy
                if name == "C":
                    xyz = np.array(
                        [[xmin + 5.0, ymin + 5.0, 120.0], [xmin + 6.0, ymin + 5.0, 121.0]]
                    )
                else:
                    xyz = _ground_and_tree(rng, xmin, ymin)
                cell = grid.cell(xmin + 10.0, ymin + 10.0)
                rel = f"tiles/{epoch}/{cell}.laz"
                cloud = PointCloud(
                    xyz,
                    {
                        "gps_time": np.arange(len(xyz), dtype=np.float64),
                        "point_source_id": np.full(len(xyz), number, dtype=np.uint16),
                    },
                )
                info = write_tile(txn.stage(rel), cloud, crs=CRS, core_bounds=grid.polygon(cell))
                row = cell_row(
                    str(cell),
                    info,
                    level=0,
                    cell_size=20.0,
                    epoch=epoch,
                    missions=[mission],
                    tile_path=rel,
                )
                rows.append(row)
                rels.append(rel)
            txn.record_mission(
                mission,
                epoch=epoch,
                date=SMALL_DATES[epoch],
                tiles=rels,
                point_count=0,
                payload_count=0,
            )
        write_index(txn.stage("index.gpkg"), crs=CRS, cells=rows)
    return root


def small_cell_id(name: str) -> str:
    """The cell id of cell ``A``..``D`` of :func:`build_small_catalog`."""
    from standgrid.partition import StandGrid

    dx, dy = next(cells[name] for cells in SMALL_CELLS.values() if name in cells)
    grid = StandGrid(CRS, 20.0)
    return str(grid.cell(SMALL_ORIGIN[0] + 20.0 * dx + 10.0, SMALL_ORIGIN[1] + 20.0 * dy + 10.0))


def tile_files(root: Path) -> dict[str, tuple[int, str]]:
    """Every tile of the catalog at ``root``: (inode, content hash) by catalog-relative path."""
    import hashlib

    from standgrid.catalog import Catalog

    catalog = Catalog.open(root)
    return {
        rel: ((root / rel).stat().st_ino, hashlib.sha256((root / rel).read_bytes()).hexdigest())
        for epoch in catalog.epochs
        for rel in catalog.tiles(epoch)
    }


def tile_points(path: Path) -> np.ndarray:
    """A tile's points (buffer copies included) as sorted rows of (x, y, z in mm, payload id,
    GPS time bits): two tiles hold the same points when these are equal."""
    from standgrid.export.las import read_tile

    cloud = read_tile(path, include_withheld=True)
    table = np.column_stack(
        [
            np.round(cloud.xyz * 1000).astype(np.int64),
            cloud.fields["payload_id"].astype(np.int64),
            cloud.fields["gps_time"].view(np.int64),
        ]
    )
    return table[np.lexsort(table.T[::-1])]


def assert_same_tiles_and_cells(a: Path, b: Path) -> dict[str, tuple[int, str]]:
    """Catalogs ``a`` and ``b`` hold the same tiles, point for point, and the same cells and
    payloads with the same point counts; ``a``'s tiles (:func:`tile_files`) are returned."""
    import pyogrio

    tiles, other = tile_files(a), tile_files(b)
    assert sorted(tiles) == sorted(other) and tiles
    for rel in tiles:
        np.testing.assert_array_equal(tile_points(a / rel), tile_points(b / rel), err_msg=rel)
    for layer, key in (("cells", "cell_id"), ("payloads", "payload_id")):
        got = pyogrio.read_dataframe(a / "index.gpkg", layer=layer).sort_values(key)
        want = pyogrio.read_dataframe(b / "index.gpkg", layer=layer).sort_values(key)
        for column in ("point_count", key):
            assert got[column].tolist() == want[column].tolist(), (layer, column)
    return tiles
