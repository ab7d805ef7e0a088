"""Throughput of the streaming PartitionEngine against a plain in-memory argsort + split.

Feeds N synthetic points (default 20 M, in 100 k-point chunks, xyz + intensity + gps_time)
through ``PartitionEngine(grid.cell_keys)`` on a 20 m grid, consuming every cell, then runs
the baseline on the same points in the same process: one ``np.argsort`` of all keys and a
split per cell (no memory bound, no spilling). Prints points/s of both, their ratio, and
peak RSS after each phase.

Example:
    python benchmarks/bench_engine.py                      # 20 M points, 512 MiB budget
    python benchmarks/bench_engine.py --budget-mib 64      # forces spilling to disk
    python benchmarks/bench_engine.py --points 2000000 --pattern uniform
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time

import numpy as np

from standgrid.partition import PartitionEngine, StandGrid
from standgrid.pointcloud import PointCloud

X0, Y0 = 600_000.0, 5_700_000.0


def make_chunk(i: int, size: int, pattern: str, extent: float) -> PointCloud:
    """Chunk ``i``: a payload-like 60 m patch moving along a lawnmower track, or uniform."""
    rng = np.random.default_rng(i)
    if pattern == "uniform":
        lo = np.array([X0, Y0])
        hi = lo + extent
    else:
        lanes = max(1, int(extent // 60))
        step = (i * 20.0) % (extent * lanes)  # a payload every 20 m of track
        lane, along = divmod(step, extent)
        x = along if int(lane) % 2 == 0 else extent - along
        lo = np.array([X0 + x - 30.0, Y0 + (lane % lanes) * 60.0])
        hi = lo + 60.0
    xy = rng.uniform(lo, hi, (size, 2))
    xyz = np.column_stack([xy, rng.uniform(0.0, 30.0, size)])
    return PointCloud(
        xyz,
        {
            "intensity": rng.integers(0, 65535, size, dtype=np.uint16),
            "gps_time": np.full(size, 1.4e9 + i, dtype=np.float64),
        },
    )


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20_000_000)
    parser.add_argument("--chunk", type=int, default=100_000)
    parser.add_argument("--budget-mib", type=float, default=512.0)
    parser.add_argument("--pattern", choices=["track", "uniform"], default="track")
    parser.add_argument("--extent", type=float, default=2000.0, help="side of the area, metres")
    args = parser.parse_args()

    grid = StandGrid("EPSG:32632", cell_size=20.0)
    n_chunks = args.points // args.chunk
    total = n_chunks * args.chunk

    # --- the engine: chunks generated on the fly (not timed), so memory stays bounded
    engine_seconds = 0.0
    with tempfile.TemporaryDirectory(prefix="bench-engine-") as workdir:
        engine = PartitionEngine(
            grid.cell_keys, workdir, memory_budget_bytes=int(args.budget_mib * 2**20)
        )
        for i in range(n_chunks):
            chunk = make_chunk(i, args.chunk, args.pattern, args.extent)
            t = time.perf_counter()
            engine.add(chunk)
            engine_seconds += time.perf_counter() - t
        t = time.perf_counter()
        checksum = 0.0
        for cell in engine.finalise():
            checksum += float(cell.core.xyz[0, 2])
        engine_seconds += time.perf_counter() - t
    engine_rss = peak_rss_mib()
    stats = engine.stats

    # --- the baseline: all points in memory, one argsort, one split
    chunks = [make_chunk(i, args.chunk, args.pattern, args.extent) for i in range(n_chunks)]
    t = time.perf_counter()
    xyz = np.concatenate([c.xyz for c in chunks])
    fields = {k: np.concatenate([c.fields[k] for c in chunks]) for k in chunks[0].fields}
    keys = grid.cell_keys(xyz[:, 0], xyz[:, 1])
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    cuts = np.flatnonzero(sorted_keys[1:] != sorted_keys[:-1]) + 1
    parts_xyz = np.split(xyz[order], cuts)
    parts_fields = {k: np.split(v[order], cuts) for k, v in fields.items()}
    baseline_cells = len(parts_xyz)
    baseline_seconds = time.perf_counter() - t
    del parts_fields
    baseline_rss = peak_rss_mib()

    assert stats.points_out == total and stats.cells == baseline_cells, (stats, baseline_cells)
    engine_rate = total / engine_seconds
    baseline_rate = total / baseline_seconds
    print(f"points            {total:,} in {n_chunks} chunks of {args.chunk:,} ({args.pattern})")
    print(f"cells             {stats.cells:,} (20 m)")
    print(f"engine            {engine_seconds:8.2f} s  {engine_rate / 1e6:7.2f} M points/s")
    print(f"baseline          {baseline_seconds:8.2f} s  {baseline_rate / 1e6:7.2f} M points/s")
    print(f"ratio             {engine_rate / baseline_rate:8.2f} (engine / argsort+split)")
    print(
        f"budget            {args.budget_mib:.0f} MiB, "
        f"spilled {stats.bytes_spilled / 2**20:.0f} MiB"
        f" in {stats.spill_flushes} flushes, peak held {stats.peak_buffered_bytes / 2**20:.0f} MiB"
    )
    print(
        f"peak RSS          {engine_rss:8.0f} MiB after the engine, "
        f"{baseline_rss:.0f} MiB after the baseline"
    )
    print(f"(checksum {checksum:.3f})")


if __name__ == "__main__":
    main()
