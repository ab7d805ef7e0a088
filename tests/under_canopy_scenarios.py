"""Whole simulated campaigns under the canopy (issue 19's acceptance): a mixed stand scanned
from below by a handheld scanner in two epochs, tiled, enriched and compared by the real
pipeline, and every figure the issue asks for measured against the simulator's truth.

``python -m tests.under_canopy_scenarios OUT SEED [HARVEST]`` runs one and prints its
figures (``tests/test_trees_under_canopy.py`` asserts them)."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from tests.tree_truth import Scores, inset_of, scores, truth_table

AREA_M = 80.0
POINTS_PER_PAYLOAD = 250_000
EDGE_M = 5.0


@dataclass(frozen=True)
class Campaigns:
    """Figures of one simulated pair of campaigns."""

    trees: dict[str, Scores]
    stands: dict[str, list[tuple[str, float, float, float, float, float]]]
    changes: dict[str, int]
    harvested: int
    harvest_found: int
    false_removed: int

    def report(self) -> str:
        lines = [f"[{e}] {s.line()}" for e, s in self.trees.items()]
        for epoch, rows in self.stands.items():
            for cell, observed, stems, stems_true, ba, ba_true in rows:
                lines.append(
                    f"[{epoch}] {cell} ({observed:.2f} ha observed): stems/ha {stems:.0f} vs "
                    f"{stems_true:.0f} ({100 * (stems / stems_true - 1):+.1f} %), basal area "
                    f"{ba:.2f} vs {ba_true:.2f} m2/ha ({100 * (ba / ba_true - 1):+.1f} %)"
                )
        lines.append(
            f"change: {self.changes}; harvest {self.harvest_found} of {self.harvested} found, "
            f"{self.false_removed} removed trees not harvested"
        )
        return "\n".join(lines)


def run(root: Path, seed: int, *, harvest: float = 0.12) -> Campaigns:
    """Simulate the pair into ``root``, run the pipeline, measure."""
    from standgrid.pipeline.run import run_pipeline
    from standgrid.simulate import load_truth, simulate_pair
    from standgrid.tiling.options import TileOptions

    simulate_pair(
        root,
        seed,
        overwrite=True,
        area=AREA_M,
        forest="mixed",
        scanner_kind="handheld",
        lane_spacing=15.0,
        points_per_payload=POINTS_PER_PAYLOAD,
        harvest_fraction=harvest,
        new_trees=3 if harvest > 0 else 0,
    )
    catalog = root / "catalog"
    run_pipeline([root / "missions"], catalog, TileOptions(overwrite=True))
    truths = {t.date[:4]: t for t in map(load_truth, sorted((root / "truth").iterdir()))}
    trees, stands = {}, {}
    metrics = pd.read_parquet(catalog / "tables/stand_metrics.parquet")
    for epoch, truth in truths.items():
        found = pd.read_parquet(catalog / f"tables/tree_list_{epoch}.parquet")
        assert truth.trees is not None
        table = truth_table(truth.trees)
        trees[epoch] = scores(found, table, inset_of(truth.bounds, EDGE_M))
        rows = metrics[(metrics["epoch"].astype(str) == epoch) & (metrics["level"] == 1)]
        stands[epoch] = []
        for row in rows[rows["stems_ha"].notna()].itertuples():
            cell = _cell_bounds(str(row.cell_id))
            ha, stems, ba = stand_truth(table, catalog / f"rasters/{epoch}/observed.tif", cell)
            stands[epoch].append(
                (str(row.cell_id), ha, row.stems_ha, stems, row.basal_area_m2_ha, ba)
            )
    changes = pd.read_parquet(next(catalog.glob("compare/*/tree_changes.parquet")))
    counts = changes["status"].value_counts().to_dict()
    later = truths[max(truths)].trees
    assert later is not None
    cut = later.status == "harvested"
    removed = changes[changes["status"] == "removed"]
    on = changes[changes["co_observed"]]
    found, false_removed, harvested = 0, 0, 0
    if cut.any():
        from scipy.spatial import cKDTree

        hx, hy = later.x_bh[cut], later.y_bh[cut]
        seen = (
            cKDTree(on[["x_from", "y_from"]].fillna(1e12).to_numpy()).query(
                np.column_stack([hx, hy])
            )[0]
            < 0.5
        )
        harvested = int(seen.sum())
        if len(removed):
            d = cKDTree(removed[["x", "y"]].to_numpy()).query(np.column_stack([hx, hy]))[0]
            found = int(((d < 0.5) & seen).sum())
            back = cKDTree(np.column_stack([hx, hy])).query(removed[["x", "y"]].to_numpy())[0]
            false_removed = int((back >= 0.5).sum())
    else:
        false_removed = len(removed)
    return Campaigns(
        trees, stands, {str(k): int(v) for k, v in counts.items()}, harvested, found, false_removed
    )


def _cell_bounds(cell_id: str) -> tuple[float, float, float, float]:
    """Bounds of a grid cell from its id (``100m_E<i>_N<j>``)."""
    size, east, north = cell_id.split("_")
    s = float(size.rstrip("m"))
    x0, y0 = float(east[1:]) * s, float(north[1:]) * s
    return x0, y0, x0 + s, y0 + s


def stand_truth(
    truth: pd.DataFrame, observed: Path, cell: tuple[float, float, float, float]
) -> tuple[float, float, float]:
    """A stand's observed area (ha, from its ``observed.tif``) and its true stems/ha and
    basal area (m²/ha) over that ground: the true trees whose stem stands on it."""
    import rasterio

    with rasterio.open(observed) as raster:
        mask = raster.read(1) == 1
        t = raster.transform
    col = np.floor((truth["x"].to_numpy() - t.c) / t.a).astype(np.int64)
    row = np.floor((truth["y"].to_numpy() - t.f) / t.e).astype(np.int64)
    ok = (row >= 0) & (row < mask.shape[0]) & (col >= 0) & (col < mask.shape[1])
    on = np.zeros(len(truth), dtype=bool)
    on[ok] = mask[row[ok], col[ok]]
    x0, y0, x1, y1 = cell
    x, y = truth["x"].to_numpy(), truth["y"].to_numpy()
    inside = on & (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
    cx = t.c + (np.arange(mask.shape[1]) + 0.5) * t.a
    cy = t.f + (np.arange(mask.shape[0]) + 0.5) * t.e
    pixels = mask & ((cy >= y0) & (cy < y1))[:, None] & ((cx >= x0) & (cx < x1))[None, :]
    ha = float(pixels.sum()) * abs(t.a * t.e) / 10_000.0
    dbh = truth["dbh"].to_numpy()[inside]
    return ha, float(inside.sum()) / ha, float(np.sum(math.pi * (dbh / 2) ** 2)) / ha


if __name__ == "__main__":
    harvest = float(sys.argv[3]) if len(sys.argv) > 3 else 0.12
    print(run(Path(sys.argv[1]), int(sys.argv[2]), harvest=harvest).report())
