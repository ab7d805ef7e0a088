"""COPC tiles (write_copc_tile) against plain LAZ tiles (write_tile), same points, same run.

Usage: python benchmarks/bench_copc.py [big_points] [n_tiles] [tile_points]
       (defaults 2,000,000 / 100 / 20,000)
       python benchmarks/bench_copc.py --tiling POINTS [--repeat N] [--workdir DIR]

``--tiling POINTS``: the issue's measure, tiling to COPC against tiling to LAZ. Simulates a
mission of about POINTS points (bench_tile's; reused from ``--workdir`` when there), then
tiles it with ``tile_missions`` to LAZ and to COPC, alternating (LAZ, COPC, LAZ, COPC, ...;
``--repeat`` pairs), each run in its own process. Prints per run the CPU seconds of the
process tree (user + sys, ``wait4``), the wall seconds and the peak RSS, then the ratios
COPC/LAZ of the best CPU and best wall against the 1.25 target.

A forest-like cloud (sloping ground, stems, crown surfaces; the fields tiles carry; random
GPS times, so no scan order to exploit) is written as one big tile and as ``n_tiles`` small
tiles, each as LAZ and as COPC, alternating. Prints points/s of both, the ratios COPC/LAZ of
the wall time and of the CPU time (this process and its threads: lazrs compresses on a
thread pool), the file sizes, and what COPC buys: reading a 1/16 corner of the big tile
through laspy's CopcReader against reading the whole LAZ tile and filtering.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import laspy
import numpy as np

from standgrid.export.copc import write_copc_tile
from standgrid.export.las import snap_to_storage, write_tile
from standgrid.pointcloud import PointCloud

CRS = "EPSG:32632"
X0, Y0, Z0 = 500_000.0, 6_000_000.0, 100.0


def forest_cloud(n: int, seed: int, size: float = 20.0) -> PointCloud:
    rng = np.random.default_rng(seed)
    n_ground, n_stem = n // 2, n // 4
    n_crown = n - n_ground - n_stem
    gx, gy = rng.uniform(0, size, n_ground), rng.uniform(0, size, n_ground)
    ground = np.column_stack([gx, gy, 0.05 * gx + rng.normal(0, 0.02, n_ground)])
    n_trees = max(int(size * size / 40), 1)
    stems = rng.uniform(1, size - 1, (n_trees, 2))
    which = rng.integers(0, n_trees, n_stem)
    angle = rng.uniform(0, 2 * np.pi, n_stem)
    radius = 0.2
    stem = np.column_stack(
        [
            stems[which, 0] + radius * np.cos(angle),
            stems[which, 1] + radius * np.sin(angle),
            rng.uniform(0, 14, n_stem),
        ]
    )
    which_c = rng.integers(0, n_trees, n_crown)
    d = rng.normal(size=(n_crown, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    crown = np.column_stack([stems[which_c] + 1.5 * d[:, :2], 16 + 3 * d[:, 2]])
    local = np.clip(np.concatenate([ground, stem, crown]), 0, size)
    xyz = snap_to_storage(local + np.array([X0, Y0, Z0]))
    return PointCloud(
        xyz,
        {
            "intensity": rng.uniform(0.0, 1.0, n).astype(np.float32),
            "gps_time": rng.uniform(1.4e9, 1.4e9 + 600, n),
            "point_source_id": np.full(n, 7, np.uint16),
            "classification": np.where(np.arange(n) < n_ground, 2, 5).astype(np.uint8),
            "payload_id": rng.integers(0, 5000, n).astype(np.uint32),
            "height_above_ground": (local[:, 2] - 0.05 * local[:, 0]).astype(np.float32),
            "tree_id": np.concatenate([np.full(n_ground, -1), which, which_c]).astype(np.int32),
        },
    )


def best_of(fn: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def best_pair(
    a: Callable[[], object], b: Callable[[], object], repeat: int
) -> tuple[tuple[float, float], tuple[float, float]]:
    """``a`` and ``b`` alternated ``repeat`` times: the least (wall, CPU) seconds of each."""
    best = [(float("inf"), float("inf"))] * 2
    for _ in range(repeat):
        for k, fn in enumerate((a, b)):
            w0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
            best[k] = (min(best[k][0], wall), min(best[k][1], cpu))
    return best[0], best[1]


def compare(label: str, clouds: list[PointCloud], folder: Path, repeat: int) -> None:
    n = sum(len(c) for c in clouds)

    def write(kind: str) -> None:
        for i, cloud in enumerate(clouds):
            if kind == "laz":
                write_tile(folder / f"{i}.laz", cloud, crs=CRS)
            else:
                write_copc_tile(folder / f"{i}.copc.laz", cloud, crs=CRS)

    (t_laz, c_laz), (t_copc, c_copc) = best_pair(
        lambda: write("laz"), lambda: write("copc"), repeat
    )
    size_laz = sum((folder / f"{i}.laz").stat().st_size for i in range(len(clouds)))
    size_copc = sum((folder / f"{i}.copc.laz").stat().st_size for i in range(len(clouds)))
    print(
        f"{label}: LAZ {n / t_laz / 1e6:.2f} Mpts/s ({t_laz:.2f} s, {c_laz:.2f} CPU-s), "
        f"COPC {n / t_copc / 1e6:.2f} Mpts/s ({t_copc:.2f} s, {c_copc:.2f} CPU-s), "
        f"ratio COPC/LAZ wall {t_copc / t_laz:.2f}, CPU {c_copc / c_laz:.2f}; "
        f"size COPC/LAZ {size_copc / size_laz:.3f} ({size_laz / n:.1f} B/pt LAZ)"
    )


def query(cloud: PointCloud, folder: Path, repeat: int) -> None:
    laz, copc = folder / "q.laz", folder / "q.copc.laz"
    write_tile(laz, cloud, crs=CRS)
    write_copc_tile(copc, cloud, crs=CRS)
    lo, hi = np.array([X0, Y0]), np.array([X0 + 5.0, Y0 + 5.0])

    def whole() -> int:
        las = laspy.read(laz)
        xy = np.column_stack([las.x, las.y])
        return int(np.all((xy >= lo) & (xy <= hi), axis=1).sum())

    def by_bounds() -> int:
        with laspy.CopcReader.open(copc) as reader:
            return len(reader.query(laspy.copc.Bounds(mins=lo, maxs=hi)))

    assert whole() == by_bounds()
    t_whole, t_query = best_of(whole, repeat), best_of(by_bounds, repeat)
    print(
        f"bounds query (1/16 of the tile, {by_bounds():,} points): read LAZ + filter "
        f"{t_whole:.3f} s, CopcReader.query {t_query:.3f} s, ratio {t_whole / t_query:.1f}x"
    )


TARGET_TILING_RATIO = 1.25


def _tile_child(mission: str, catalog: str, fmt: str) -> None:
    """One timed tiling run (in a child process): prints points and VmHWM as JSON."""
    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions

    shutil.rmtree(catalog, ignore_errors=True)
    options = TileOptions(laz=True, copc=fmt == "copc", overwrite=True)
    report = tile_missions([Path(mission)], Path(catalog), options)
    assert report.points_in == report.points_out
    hwm = next(
        int(line.split()[1]) / 1024
        for line in Path("/proc/self/status").read_text().splitlines()
        if line.startswith("VmHWM:")
    )
    print(json.dumps({"points": report.points_out, "peak_mb": hwm}))


def _timed_child(*args: str) -> dict[str, float]:
    """A child run of this script: its CPU seconds (user + sys of the tree), wall, output."""
    os.sync()
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, __file__, "--child", *args], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    out = proc.stdout.read()
    _pid, status, usage = os.wait4(proc.pid, 0)  # the child and its reaped descendants
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"child {args} failed ({proc.returncode})")
    result = json.loads(out.strip().splitlines()[-1])
    return {**result, "cpu": usage.ru_utime + usage.ru_stime, "wall": wall}


def tiling(points: int, repeat: int, workdir: Path | None) -> None:
    """Tile one simulated mission to LAZ and to COPC, alternating; print the ratios."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_tile import run_child  # the simulation (cached under the work folder)

    work = workdir or Path(tempfile.mkdtemp(prefix="bench_copc_tiling_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        existing = sorted((work / "sim" / "missions").glob("*"))
        if existing:
            mission = str(existing[0])
        else:
            mission = run_child("simulate", str(work / "sim"), str(points), "200")["mission"]
        runs: dict[str, list[dict[str, float]]] = {"laz": [], "copc": []}
        for i in range(repeat):
            for fmt in ("laz", "copc"):
                r = _timed_child("tile", mission, str(work / f"catalog_{fmt}"), fmt)
                runs[fmt].append(r)
                print(
                    f"run {i + 1} tile {fmt:<4}: {r['points']:,} points, CPU {r['cpu']:.2f} s, "
                    f"wall {r['wall']:.2f} s, peak RSS {r['peak_mb']:.0f} MB",
                    flush=True,
                )
        best = {
            fmt: {k: min(r[k] for r in rs) for k in ("cpu", "wall", "peak_mb")}
            for fmt, rs in runs.items()
        }
        cpu = best["copc"]["cpu"] / best["laz"]["cpu"]
        wall = best["copc"]["wall"] / best["laz"]["wall"]
        verdict = "met" if cpu <= TARGET_TILING_RATIO else "NOT met"
        print(
            f"tiling COPC/LAZ (best of {repeat}): CPU {cpu:.2f}x "
            f"({best['copc']['cpu']:.1f} / {best['laz']['cpu']:.1f} s), wall {wall:.2f}x "
            f"({best['copc']['wall']:.1f} / {best['laz']['wall']:.1f} s), peak RSS "
            f"{best['copc']['peak_mb']:.0f} / {best['laz']['peak_mb']:.0f} MB; "
            f"target <= {TARGET_TILING_RATIO}x CPU: {verdict}"
        )
    finally:
        if workdir is None:
            shutil.rmtree(work, ignore_errors=True)


def main() -> None:
    if sys.argv[1:2] == ["--child"]:
        _tile_child(*sys.argv[3:6])
        return
    if sys.argv[1:2] == ["--tiling"]:
        args = sys.argv[3:]
        repeat = int(args[args.index("--repeat") + 1]) if "--repeat" in args else 2
        workdir = Path(args[args.index("--workdir") + 1]) if "--workdir" in args else None
        tiling(int(sys.argv[2]), repeat, workdir)
        return
    big = int(sys.argv[1]) if len(sys.argv) > 1 else 2_000_000
    n_tiles = int(sys.argv[2]) if len(sys.argv) > 2 else 100
    per_tile = int(sys.argv[3]) if len(sys.argv) > 3 else 20_000
    big_cloud = forest_cloud(big, seed=0)
    small = [forest_cloud(per_tile, seed=1 + i) for i in range(n_tiles)]
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        compare(f"1 tile of {big:,}", [big_cloud], folder, repeat=3)
        compare(f"{n_tiles} tiles of {per_tile:,}", small, folder, repeat=2)
        query(big_cloud, folder, repeat=3)


if __name__ == "__main__":
    main()
