"""Simulated campaigns over partly overlapping ground, and their truth per stand.

Two missions over one stand walk different irregular survey polygons (epoch 1 the west,
epoch 2 the east, overlapping in the middle); between them the forest grows and,
optionally, one 1 ha stand is harvested. ``run_scenario`` tiles, enriches and compares
them; ``truth_per_stand`` gives the simulator's stems/ha and basal area over exactly the
ground a stand row was measured on (its observed pixels), so estimates and truth compare
like with like.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

#: Survey polygons in stand-local units (fractions of the stand side).
WEST = ((0.0, 0.0), (0.72, 0.0), (0.62, 0.3), (0.8, 0.62), (0.68, 1.0), (0.0, 1.0))
EAST = ((0.3, 0.0), (1.0, 0.0), (1.0, 1.0), (0.36, 1.0), (0.2, 0.66), (0.32, 0.34))


@dataclass
class Scenario:
    root: Path
    catalog: Path
    missions: list[Path]
    truth: list[Path]
    bounds: tuple[float, float, float, float]
    harvest_stand: str | None


def _scaled(polygon: tuple[tuple[float, float], ...], side: float) -> tuple[Any, ...]:
    return tuple((u * side, v * side) for u, v in polygon)


def run_scenario(
    root: Path,
    *,
    seed: int,
    area: float,
    points_per_payload: int,
    harvest: bool,
    enrich_options: Any = None,
) -> Scenario:
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.partition import StandGrid
    from standgrid.pipeline.compare import compare_epochs
    from standgrid.pipeline.enrich import enrich_catalog
    from standgrid.pipeline.tile import tile_missions
    from standgrid.simulate.mission import simulate_mission, stand_bounds
    from standgrid.tiling.options import TileOptions

    bounds = stand_bounds(area)
    grid = StandGrid("EPSG:32630")
    # the harvest: 45 % of the trees of the 1 ha stand at the middle of the overlap
    cx, cy = bounds[0] + 0.5 * area, bounds[1] + 0.5 * area
    stand = grid.cell(cx, cy, level=1) if harvest else None
    box = None
    if stand is not None:
        x0, y0, x1, y1 = grid.polygon(stand).bounds
        box = (x0 - bounds[0], y0 - bounds[1], x1 - bounds[0], y1 - bounds[1])
    common = {
        "area": area,
        "points_per_payload": points_per_payload,
        "harvest_fraction": 0.45 if harvest else 0.0,
        "harvest_box": box,
        "new_trees": 3 if harvest else 0,
    }
    sims = [
        simulate_mission(root, seed=seed, epoch=1, survey_polygon=_scaled(WEST, area), **common),
        simulate_mission(root, seed=seed, epoch=2, survey_polygon=_scaled(EAST, area), **common),
    ]
    missions = [s.mission_dir for s in sims]
    catalog = root / "catalog"
    tile_missions(missions, catalog, TileOptions())
    enrich_catalog(catalog, enrich_options or EnrichOptions())
    compare_epochs(catalog)
    return Scenario(
        root,
        catalog,
        missions,
        [s.truth_dir for s in sims],
        bounds,
        str(stand) if stand is not None else None,
    )


def observed_mask(catalog: Path, epoch: str) -> Any:
    from standgrid.geotiff import read_raster

    raster = read_raster(catalog / f"rasters/{epoch}/observed.tif")
    return raster.array == 1, raster.grid


def truth_trees(truth_dir: Path) -> pd.DataFrame:
    """Trees standing at the truth's epoch."""
    trees = pd.read_csv(truth_dir / "trees.csv")
    return trees[trees["status"] != "harvested"].reset_index(drop=True)


def truth_per_stand(
    metrics: pd.DataFrame, trees: pd.DataFrame, mask: Any, grid: Any, catalog_grid: Any
) -> pd.DataFrame:
    """Truth stems/ha and basal area (m2/ha) over each stand row's observed ground.

    A cell's ground is its observed pixels; a 1 ha stand's is the observed pixels of its
    measured cells (as enrich aggregates them)."""
    from standgrid.enrichment.coverage import sample_mask
    from standgrid.partition import CellId

    on = sample_mask(mask, grid, trees["x"].to_numpy(), trees["y"].to_numpy())
    t = trees[on]
    cells = [str(catalog_grid.cell(x, y)) for x, y in zip(t["x"], t["y"], strict=True)]
    t = t.assign(cell=cells, ba=np.pi * (t["dbh_m"] / 2.0) ** 2)
    t = t.assign(stand=[str(CellId.parse(c).parent(catalog_grid)) for c in cells])
    level0 = metrics[metrics["level"] == 0]
    measured_cells = set(level0.loc[level0["stems_ha"].notna(), "cell_id"])
    rows = []
    for row in metrics.itertuples():
        if row.level == 0:
            mine = t[t["cell"] == row.cell_id]
        else:
            mine = t[(t["stand"] == row.cell_id) & t["cell"].isin(measured_cells)]
        ha = row.observed_m2 / 10_000.0
        rows.append(
            {
                "cell_id": row.cell_id,
                "truth_stems_ha": len(mine) / ha if ha > 0 else math.nan,
                "truth_basal_area_m2_ha": mine["ba"].sum() / ha if ha > 0 else math.nan,
            }
        )
    return metrics.merge(pd.DataFrame(rows), on="cell_id")
