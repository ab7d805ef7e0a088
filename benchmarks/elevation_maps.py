"""Payload elevation maps end to end: a simulated mission carrying them (a known bias and
noise against the terrain truth), tiled and enriched; the epoch mosaic against the truth
and against the DTM from points, and the DTM against the truth.

Usage::

    python benchmarks/elevation_maps.py [--workdir DIR] [--area 120] [--seed 0]
                                        [--points-per-payload 30000]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np


def _stats(diff: np.ndarray) -> dict[str, Any]:
    diff = diff[np.isfinite(diff)]
    median = float(np.median(diff))
    return {
        "pixels": int(diff.size),
        "median_m": round(median, 4),
        "mad_m": round(1.4826 * float(np.median(np.abs(diff - median))), 4),
        "rmse_m": round(float(np.sqrt(np.mean(diff**2))), 4),
    }


def main() -> None:
    from standgrid.api import enrich, tile
    from standgrid.catalog import paths
    from standgrid.geotiff import read_raster
    from standgrid.simulate import simulate_mission
    from standgrid.simulate.elevation import ElevationMapModel
    from standgrid.simulate.mission import SimulationConfig
    from standgrid.simulate.terrain import Terrain

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workdir", type=Path)
    parser.add_argument("--area", type=float, default=120.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--points-per-payload", type=int, default=30_000)
    args = parser.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="elevation-maps-"))
    model = ElevationMapModel()
    config = SimulationConfig(
        area=args.area, points_per_payload=args.points_per_payload, elevation_maps=model
    )
    sim = simulate_mission(work / "sim", seed=args.seed, epoch=1, overwrite=True, config=config)
    catalog = work / "catalog"
    shutil.rmtree(catalog, ignore_errors=True)
    tiled = tile([sim.mission_dir], catalog)
    epoch = next(iter(tiled.epochs))
    enriched = enrich(catalog)
    truth = json.loads((sim.truth_dir / "truth.json").read_text())
    terrain = Terrain.from_dict(truth["terrain"])
    out: dict[str, Any] = {"simulated_error": truth["elevation_maps"]}
    for name in (paths.ELEVATION_MAP, "dtm"):
        raster = read_raster(catalog / paths.raster(epoch, name))
        cx, cy = raster.grid.centers()
        out[f"{name}_minus_truth"] = _stats(raster.array - terrain.height(cx, cy))
    out["elevation_map_minus_dtm"] = enriched.epochs[epoch]["elevation_map_minus_dtm"]
    out["mosaic"] = tiled.epochs[epoch]["elevation_map"]
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
