"""Tile a mission far larger than the engine's memory budget; print throughput and peak RSS.

    python benchmarks/bench_tile_bounded_memory.py [--area 360] [--points-per-payload 600000]
        [--budget-mb 512] [--workdir /tmp/standgrid-big]

The defaults simulate ~146 M points (~85 s, ~4 GB of PCD) and tile them with a 512 MB budget:
the engine spills to disk and peak memory stays bounded by the budget, not the mission.
Baseline in the same run: the peak RSS after simulating (the process's own floor).
"""

from __future__ import annotations

import argparse
import resource
import shutil
import time
from pathlib import Path


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    from standgrid.engine import MemoryBudget
    from standgrid.pipeline.tile import TileOptions, tile_missions
    from standgrid.simulate import simulate_mission

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--area", type=float, default=360.0)
    parser.add_argument("--points-per-payload", type=int, default=600_000)
    parser.add_argument("--budget-mb", type=int, default=512)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/standgrid-big"))
    args = parser.parse_args()

    missions = args.workdir / "sim" / "missions"
    if not missions.exists():
        start = time.perf_counter()
        simulate_mission(
            args.workdir / "sim",
            seed=3,
            area=args.area,
            points_per_payload=args.points_per_payload,
            overwrite=True,
        )
        print(f"simulated in {time.perf_counter() - start:.0f} s", flush=True)
    floor = _peak_mb()
    mission = next(missions.iterdir())
    catalog = args.workdir / "catalog"
    shutil.rmtree(catalog, ignore_errors=True)
    start = time.perf_counter()
    options = TileOptions(memory_budget=MemoryBudget.megabytes(args.budget_mb))
    report = tile_missions([mission], catalog, options)
    seconds = time.perf_counter() - start
    epoch = next(iter(report.epochs.values()))
    print(f"points in / out    {report.points_in:,} / {report.points_out:,}")
    print(f"tiles              {epoch['cells']}")
    print(f"throughput         {report.points_in / seconds / 1e6:.2f} M points/s ({seconds:.1f} s)")
    print(
        f"engine budget      {args.budget_mb} MB, spilled {epoch['bytes_spilled'] / 2**20:,.0f} MB"
    )
    print(f"peak RSS           {_peak_mb():,.0f} MB (before tiling: {floor:,.0f} MB)")
    print(f"data size          {report.points_in * 42 / 2**20:,.0f} MB as engine records")


if __name__ == "__main__":
    main()
