"""``enrich_catalog`` throughput against a plain laspy read + write of the same tiles, same run.

Usage::

    python benchmarks/bench_enrich.py [--points 20000000] [--area 200] [--workdir DIR]
                                      [--workers 0,1,2] [--memory MB] [--scan LAS ...]

1. Simulates one mission of about ``--points`` points (``standgrid.simulate``), or with
   ``--scan`` cuts real georeferenced scans into a mission (``mission_from_scan``, e.g. the
   four ``../shared/data/real/als/lasR_bcts/*.laz``), and tiles it into a LAZ catalog
   (20 m grid); both are reused from ``--workdir`` when present.
2. Baseline: every tile read with ``laspy.read`` and written again with ``LasData.write``
   (LAZ, lazrs, one thread), one process.
3. Enrichment of a fresh copy of the catalog, once per entry of ``--workers``: 0 = this
   process; N = a dask LocalCluster of N single-threaded worker processes, started before
   the clock (its start-up time is printed apart).

Every measurement runs in its own subprocess (its peak RSS is its own; with a cluster the
workers' peaks are reported too). Prints points/s, the ratio enrich / baseline (target
>= 0.3 in one process) and, with several worker counts, the speed-up over 1 worker; and
each process's peak RSS against ``--memory``: peak / budget and whether ``peak - interpreter
<= 1.1 x budget`` (issue 22), the interpreter being a child that imports what enrichment
imports and does nothing. ``--no-copy`` skips the laspy baseline.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))


def _peak_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def measure_tile(mission: Path, catalog: Path) -> dict[str, Any]:
    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions

    t0 = time.perf_counter()
    report = tile_missions([mission], catalog, TileOptions(overwrite=True))
    return {"seconds": time.perf_counter() - t0, "points": report.points_out}


def measure_copy(catalog: Path, out: Path) -> dict[str, Any]:
    import laspy

    out.mkdir(parents=True, exist_ok=True)
    tiles = sorted(catalog.glob("tiles/*/*.la[sz]"))
    points = 0
    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    for tile in tiles:
        las = laspy.read(tile)
        las.write(out / tile.name)
        points += len(las.points)
    seconds = time.perf_counter() - t0
    return {
        "seconds": seconds,
        "points": points,
        "tiles": len(tiles),
        "cpu_seconds": _cpu_seconds() - cpu0,
    }


def measure_enrich(catalog: Path, workers: int, memory_mb: int) -> dict[str, Any]:
    import pyogrio

    from standgrid.engine import Execution, open_executor
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.pipeline.enrich import enrich_catalog

    cells = pyogrio.read_dataframe(catalog / "index.gpkg", layer="cells", read_geometry=False)
    points = int(cells["point_count"].sum())
    options = EnrichOptions()
    execution = Execution(memory_mb=memory_mb)
    t0 = time.perf_counter()
    # a cluster is started before the clock (as bench_tile does; its start-up is printed apart)
    with open_executor(workers or None, memory_budget=execution.memory_budget.bytes) as executor:
        started = time.perf_counter() - t0
        cpu0 = _cpu_seconds() + _workers_cpu_seconds(executor)
        t1 = time.perf_counter()
        report = enrich_catalog(catalog, options, execution=execution.on(executor))
        seconds = time.perf_counter() - t1
        cpu = _cpu_seconds() + _workers_cpu_seconds(executor) - cpu0
        client = getattr(executor, "client", None)
        worker_peaks = sorted(client.run(_peak_mb).values()) if client is not None else []
    epoch = next(iter(report.epochs.values()))
    return {
        "seconds": seconds,
        "cluster_start_seconds": started,
        "points": points,
        "cells": epoch["cells"],
        "chunks": epoch["chunks"],
        "trees": epoch["trees"],
        "cpu_seconds": cpu,
        "worker_peaks_mb": worker_peaks,
    }


def measure_imports() -> dict[str, Any]:
    """Nothing but the imports enrichment makes (its lazy ones too): the interpreter's own
    peak."""
    import laspy  # noqa: F401
    import numpy  # noqa: F401
    import pyogrio  # noqa: F401
    import rasterio.features  # noqa: F401
    import scipy.ndimage
    import scipy.spatial  # noqa: F401
    import shapely  # noqa: F401
    import skimage.measure
    import skimage.segmentation  # noqa: F401

    import standgrid.enrichment.block
    import standgrid.pipeline.enrich  # noqa: F401

    return {}


def measure_warm() -> dict[str, Any]:
    """The interpreter once enrichment has run (every lazy import, library caches): tile
    and enrich the bundled demo mission, free what can be freed, and report the RSS left."""
    import gc

    from standgrid.engine.budget import release_memory
    from standgrid.pipeline.enrich import enrich_catalog
    from standgrid.pipeline.tile import tile_missions

    with tempfile.TemporaryDirectory() as tmp:
        mission = next((REPO / "data" / "missions").iterdir())
        tile_missions([mission], Path(tmp) / "demo")
        enrich_catalog(Path(tmp) / "demo")
    gc.collect()
    release_memory()
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return {"rss_mb": int(line.split()[1]) / 1024}
    return {"rss_mb": float("nan")}


def _cpu_seconds() -> float:
    """User + system CPU time of this process, every thread."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _workers_cpu_seconds(executor: Any) -> float:
    """The same, summed over a cluster's worker processes (0 without a cluster)."""
    client = getattr(executor, "client", None)
    return sum(client.run(_cpu_seconds).values()) if client is not None else 0.0


def _child(args: list[str]) -> None:
    kind, *rest = args
    if kind == "simulate":
        from bench_tile import measure_simulate

        result = measure_simulate(Path(rest[0]), int(rest[1]), float(rest[2]))
    elif kind == "scan":
        from standgrid.simulate import mission_from_scan

        made = mission_from_scan(rest[1:], Path(rest[0]), seed=5)
        result = {"points": int(made.n_points), "seconds": 0.0}
    elif kind == "tile":
        result = measure_tile(Path(rest[0]), Path(rest[1]))
    elif kind == "imports":
        result = measure_imports()
    elif kind == "warm":
        result = measure_warm()
    elif kind == "copy":
        result = measure_copy(Path(rest[0]), Path(rest[1]))
    else:
        result = measure_enrich(Path(rest[0]), int(rest[1]), int(rest[2]))
    result["peak_mb"] = _peak_mb()
    print(json.dumps(result))


def run_child(*args: str) -> dict[str, Any]:
    """One measurement in its own process, started after an (untimed) ``sync`` so writes
    left in flight by the previous one do not slow it down."""
    os.sync()
    out = subprocess.run(
        [sys.executable, __file__, "--child", *args], check=True, capture_output=True, text=True
    )
    result: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20_000_000)
    parser.add_argument("--area", type=float, default=200.0)
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--workers", default="0", help="comma-separated, 0 = this process")
    parser.add_argument("--memory", type=int, default=2048, help="budget per process, MB")
    parser.add_argument("--scan", nargs="+", default=None, help="real LAS/LAZ scans")
    parser.add_argument("--no-copy", action="store_true", help="skip the laspy baseline")
    opts = parser.parse_args()
    work = opts.workdir or Path(tempfile.mkdtemp(prefix="standgrid-bench-enrich-"))
    work.mkdir(parents=True, exist_ok=True)
    missions = work / "sim"
    catalog = work / "catalog"
    if not (catalog / "catalog.json").exists():
        if not (missions / "missions").exists() and opts.scan:
            made = run_child("scan", str(missions), *opts.scan)
            print(f"cut {made['points']:,} points of {len(opts.scan)} real scans into a mission")
        elif not (missions / "missions").exists():
            sim = run_child("simulate", str(missions), str(opts.points), str(opts.area))
            print(f"simulated {sim['points']:,} points in {sim['seconds']:.0f} s")
        mission = next((missions / "missions").iterdir())
        tiled = run_child("tile", str(mission), str(catalog))
        print(f"tiled {tiled['points']:,} points in {tiled['seconds']:.1f} s")
    base_pps = float("nan")
    if not opts.no_copy:
        copy = run_child("copy", str(catalog), str(work / "copy"))
        shutil.rmtree(work / "copy")
        base_pps = copy["points"] / copy["seconds"]
        print(
            f"baseline laspy read+write of {copy['tiles']} LAZ tiles: {copy['seconds']:.1f} s, "
            f"{base_pps / 1e6:.2f} M points/s, peak {copy['peak_mb']:.0f} MB"
        )
        per_million = copy["cpu_seconds"] / (copy["points"] / 1e6)
        print(
            f"  its CPU: {per_million:.2f} s per M points (reading and writing the tiles "
            f"alone): 1 M points per CPU-second leaves {1 - per_million:.2f} s per M points "
            "for ground, terrain, trees and metrics"
        )
    interpreter = run_child("imports")["peak_mb"]
    warm = run_child("warm")["rss_mb"]
    print(
        f"interpreter (imports only): peak {interpreter:.0f} MB; warm (after enriching the "
        f"demo: every lazy import and library cache): {warm:.0f} MB"
    )
    by_workers = {}
    for workers in (int(w) for w in opts.workers.split(",")):
        run = work / f"enrich-{workers}"
        shutil.rmtree(run, ignore_errors=True)
        shutil.copytree(catalog, run)
        result = run_child("enrich", str(run), str(workers), str(opts.memory))
        shutil.rmtree(run)
        pps = result["points"] / result["seconds"]
        by_workers[workers] = result["seconds"]
        where = "this process" if workers == 0 else f"LocalCluster of {workers} worker(s)"
        print(
            f"enrich ({where}): {result['points']:,} points, {result['cells']} cells in "
            f"{result['chunks']} chunks, {result['trees']} trees: {result['seconds']:.1f} s, "
            f"{pps / 1e6:.2f} M points/s, ratio to baseline {pps / base_pps:.2f} "
            f"(target >= 0.3 in one process); CPU {result['cpu_seconds']:.1f} s = "
            f"{result['points'] / result['cpu_seconds'] / 1e6:.2f} M points per CPU-second "
            f"(target >= 1 per core), client peak {result['peak_mb']:.0f} MB"
            + (f"; cluster started in {result['cluster_start_seconds']:.1f} s" if workers else "")
        )
        names = ["client", *(f"worker {k}" for k in range(len(result["worker_peaks_mb"])))]
        for name, peak in zip(names, [result["peak_mb"], *result["worker_peaks_mb"]], strict=True):
            ok = peak - interpreter <= 1.1 * opts.memory
            ok_warm = peak - warm <= 1.1 * opts.memory
            print(
                f"  {name:9s} peak RSS {peak:6.0f} MB, peak / budget {peak / opts.memory:.2f}, "
                f"peak - interpreter {peak - interpreter:6.0f} MB <= 1.1 x budget "
                f"({1.1 * opts.memory:.0f} MB)? {'yes' if ok else 'NO'}; peak - warm "
                f"interpreter {peak - warm:6.0f} MB? {'yes' if ok_warm else 'NO'}"
            )
    if 1 in by_workers and 2 in by_workers:
        print(f"2 workers vs 1 worker: {by_workers[1] / by_workers[2]:.2f}x (target >= 1.7)")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _child(sys.argv[2:])
    else:
        main()
