"""Area-based stand metrics throughput, against ``np.sort`` of the same heights in the same run.

Usage: python benchmarks/bench_metrics.py [--points 5000000] [--cells 2500] [--repeat 3]
Prints points per second of ``area_metrics`` and its time as a multiple of one ``np.sort``
of the heights (the least any exact percentile computation must do). Target: >= 5 M points/s.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from standgrid.enrichment.metrics import area_metrics


def best_of(repeat: int, func: object) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        func()  # type: ignore[operator]
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=5_000_000)
    parser.add_argument("--cells", type=int, default=2500, help="stand cells (50 x 50 of 20 m)")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    side = int(np.sqrt(args.cells))
    x = rng.uniform(0, side * 20.0, args.points)
    y = rng.uniform(0, side * 20.0, args.points)
    cell = (np.floor(y / 20.0).astype(np.int64) << 32) | np.floor(x / 20.0).astype(np.int64)
    heights = np.where(
        rng.random(args.points) < 0.3,
        rng.normal(0, 0.05, args.points),
        rng.gamma(4.0, 4.0, args.points),
    )

    baseline = best_of(args.repeat, lambda: np.sort(heights))
    metrics = best_of(args.repeat, lambda: area_metrics(cell, heights, cell_area_m2=400.0))
    table = area_metrics(cell, heights, cell_area_m2=400.0)
    print(f"points: {args.points:,}  cells: {len(table):,}  metric columns: {table.shape[1]}")
    print(f"np.sort baseline: {baseline:.3f} s  ({args.points / baseline / 1e6:.1f} M points/s)")
    print(f"area_metrics:     {metrics:.3f} s  ({args.points / metrics / 1e6:.1f} M points/s)")
    print(f"ratio area_metrics / np.sort: {metrics / baseline:.2f}")


if __name__ == "__main__":
    main()
