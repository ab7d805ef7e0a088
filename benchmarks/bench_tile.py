"""``tile_missions`` throughput against a plain laspy copy of the same points, same run.

Usage::

    python benchmarks/bench_tile.py [--points 20000000] [--area 200] [--workdir DIR] [--keep]
                                    [--blas-threads N] [--repeat N] [--workers 1,2] [--no-copy]
                                    [--warm]

1. Simulates one mission of about ``--points`` points (``standgrid.simulate``); a mission
   already simulated under ``--workdir`` (kept with ``--keep``) is reused.
2. Tiles it into a fresh catalog twice: LAZ, then LAS (timed: the whole ``tile_missions``
   call, georeference included).
3. Baseline: the same points (the LAS tiles merged, same point format and extra bytes) are
   written beforehand as one LAS and one LAZ file with laspy (not timed); the timed copy is
   ``laspy.read`` + ``LasData.write`` of that file, in LAZ and LAS.

Every measurement runs in its own subprocess, so the peak memory (``VmHWM``, and
``ru_maxrss``) is that measurement's alone. Prints points/s of each, the throughput ratio
tile / copy (target >= 0.8) and the peaks; ``--repeat N`` keeps the fastest of N runs of
each measurement (the machine may be shared). ``--blas-threads N`` sets OPENBLAS_NUM_THREADS
(and OMP/MKL) in the children: on a busy machine multi-threaded BLAS in the small
``(N, 3) @ (3, 3)`` products of the tiler can cost more than it gains.

4. Floor: the least any tiler of these payloads does, in plain numpy on two threads (read
   the binary PCD payloads, one affine each, 20 m cell keys, a stable sort, gather per cell
   into records of the tiles' length, write + fsync a file per cell; no fit, buffers,
   fields, headers, index or checks). Printed against the copy and against ``tile``: where
   even the floor is below the target ratio, no numpy tiler reaches it on this machine.

Every measurement starts after an (untimed) ``sync``, so no writes left in flight by the
previous one (the baseline files are written without fsync) slow it down.

``--workers 1,2`` also tiles (LAZ) on a dask LocalCluster of each number of worker
processes and prints the speed-up of the last over the first (target >= 1.7 for 1 -> 2 on
two cores). The cluster is started before the clock starts (its start-up is printed
apart); the peak memory printed is the client's (workers are limited by the budget).
``--no-copy`` skips the tile-vs-copy part. ``--warm`` times tiling in a process that has
tiled the bundled demo mission first (libraries imported, as laspy is for the copy); without
it the clock includes importing what tiling needs (about 1 s).

``--fixed-cost`` measures what a small job pays before its first point, on its own: a tiny
simulated mission (``--tiny-points``, a few thousand points) tiled by the real command
(``standgrid tile``, a fresh process each run) against interpreter start (``python -c
pass``) and ``python -c "import standgrid.cli"`` in the same run. Prints CPU seconds
(user + sys of the whole process, from ``wait4``) and wall seconds, the best of
``--repeat`` runs, the ratios to the interpreter start, and which heavy libraries the tile
command imported. Children write bytecode to a private cache (warmed first), so the figures
do not include compiling sources when the environment sets ``PYTHONDONTWRITEBYTECODE``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

SEED = 11
TARGET_RATIO = 0.8
TARGET_SPEEDUP = 1.7


#: Libraries a small ``standgrid tile`` should not need (reported by ``--fixed-cost``).
HEAVY_MODULES = ("pandas", "geopandas", "pyarrow", "scipy.spatial", "standgrid.alignment")


def _peak_mb() -> dict[str, float]:
    """This process's peak resident memory (MB): VmHWM of its own address space, ru_maxrss."""
    hwm = math.nan
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                hwm = int(line.split()[1]) / 1024
    except OSError:
        pass
    return {"peak_mb": hwm, "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


# --- measurements (each in a child process) ----------------------------------------------


def measure_simulate(root: Path, points: int, area: float) -> dict[str, Any]:
    from standgrid.simulate import SimulationConfig, simulate_mission
    from standgrid.simulate.mission import run_simulation

    spans = len(run_simulation(SEED, 1, SimulationConfig(area=area)).spans)
    # the scanner keeps ~98.5 % of the rays it is asked for
    per_payload = max(1000, math.ceil(points / spans / 0.985))
    t0 = time.perf_counter()
    sim = simulate_mission(root, seed=SEED, area=area, points_per_payload=per_payload)
    return {
        "seconds": time.perf_counter() - t0,
        "points": sim.n_points,
        "payloads": len(sim.spans),
        "mission": str(sim.mission_dir),
    }


def measure_tile(mission: Path, catalog: Path, laz: bool, warm: bool = False) -> dict[str, Any]:
    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions

    if warm:  # a process that has tiled before: libraries imported, caches built (the copy's
        # clock, too, starts after laspy is imported)
        small = sorted((Path(__file__).resolve().parents[1] / "data" / "missions").iterdir())[0]
        with tempfile.TemporaryDirectory() as scratch:
            tile_missions([small], Path(scratch) / "c", TileOptions(laz=laz))
    t0 = time.perf_counter()
    report = tile_missions([mission], catalog, TileOptions(laz=laz, overwrite=True))
    seconds = time.perf_counter() - t0
    assert report.points_in == report.points_out
    epoch = next(iter(report.epochs.values()))
    return {
        "seconds": seconds,
        "points": report.points_out,
        "tiles": epoch["cells"],
        "bytes_spilled": epoch["bytes_spilled"],
    }


def measure_tile_workers(mission: Path, catalog: Path, workers: int) -> dict[str, Any]:
    """Tile (LAZ) on a LocalCluster of ``workers`` processes, started before the clock."""
    from standgrid.engine import Execution, open_executor
    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions

    t0 = time.perf_counter()
    with open_executor(workers=workers) as executor:
        started = time.perf_counter() - t0
        t1 = time.perf_counter()
        options = TileOptions(laz=True, overwrite=True)
        report = tile_missions([mission], catalog, options, execution=Execution(executor=executor))
        seconds = time.perf_counter() - t1
    assert report.points_in == report.points_out and report.workers == workers
    return {"seconds": seconds, "startup_seconds": started, "points": report.points_out}


def measure_baseline_files(catalog: Path, las_out: Path, laz_out: Path) -> dict[str, Any]:
    """Merge the (LAS) tiles into one LAS and one LAZ file with laspy: the copy's input."""
    import laspy
    import numpy as np

    tiles = sorted(catalog.glob("tiles/*/*.las"))
    first = laspy.read(tiles[0])
    header = first.header
    xyz_min = np.full(3, np.inf)
    for path in tiles:
        with laspy.open(path) as reader:
            xyz_min = np.minimum(xyz_min, reader.header.mins)
    offsets = np.floor(xyz_min)
    parts = []
    for path in tiles:
        las = laspy.read(path)
        record = las.points.array.copy()
        for axis, upper in enumerate("XYZ"):
            coords = np.asarray(las.xyz[:, axis])
            record[upper] = np.round((coords - offsets[axis]) / header.scales[axis]).astype(
                np.int32
            )
        parts.append(record)
    header.offsets = offsets
    merged = laspy.LasData(
        header, laspy.PackedPointRecord(np.concatenate(parts), header.point_format)
    )
    merged.update_header()
    merged.write(las_out)
    with open(laz_out, "wb") as stream:
        merged.write(stream, do_compress=True, laz_backend=laspy.LazBackend.LazrsParallel)
    return {"points": len(merged.points)}


def measure_copy(source: Path, target: Path, laz: bool) -> dict[str, Any]:
    import laspy

    backend = laspy.LazBackend.LazrsParallel if laz else None
    t0 = time.perf_counter()
    las = laspy.read(source, laz_backend=backend) if laz else laspy.read(source)
    with open(target, "wb") as stream:
        las.write(stream, do_compress=laz, laz_backend=backend)
    return {"seconds": time.perf_counter() - t0, "points": len(las.points)}


def measure_floor(mission: Path, catalog: Path, out: Path) -> dict[str, Any]:
    """The least any tiler of these payloads does, in plain numpy on two threads: read each
    binary PCD payload, float64 coordinates, one affine (its node pose; applied, not fitted),
    20 m cell keys, a stable sort; then per cell gather its points from every payload into
    LAS-sized records (the tiles' record length) of 1 mm integers and intensity, write and
    fsync one file per cell. No georeference fit, no buffers, fields, header, index or
    checks: a lower bound on tiling's time, measured the same way as the copy."""
    from concurrent.futures import ThreadPoolExecutor

    import laspy
    import numpy as np
    from threadpoolctl import threadpool_limits

    from standgrid import open_mission

    opened = open_mission(mission)
    items = []
    for payload in opened.payloads:
        if payload.kind != "point_cloud":
            continue
        pose = opened.pose_of(payload)
        to_base = opened.file_to_base(payload)
        items.append((payload.path, pose if to_base is None else pose @ to_base))
    with laspy.open(next(catalog.glob("tiles/*/*.las"))) as reader:
        record_bytes = reader.header.point_format.size
    shift = np.array([500_000.0, 5_700_000.0, 100.0])  # a UTM-like magnitude

    def load(item: tuple[Path, Any]) -> tuple[Any, Any, Any]:
        path, pose = item
        with open(path, "rb") as stream:
            head = b""
            while not head.endswith(b"DATA binary\n"):
                line = stream.readline()
                if not line or (line.startswith(b"DATA") and line.strip() != b"DATA binary"):
                    raise SystemExit(f"the floor reads binary PCD payloads only: {path}")
                head += line
            fields = dict(
                (words[0], words[1:]) for words in (row.split() for row in head.splitlines())
            )
            names = [n.decode() for n in fields[b"FIELDS"]]
            kinds = [
                f"<{t.decode().lower()}{s.decode()}"
                for t, s in zip(fields[b"TYPE"], fields[b"SIZE"], strict=True)
            ]
            data = np.fromfile(stream, dtype=list(zip(names, kinds, strict=True)))
        xyz = np.stack([data[a] for a in "xyz"], axis=1).astype(np.float64)
        xyz = xyz @ pose[:3, :3].T + (pose[:3, 3] + shift)
        keys = (np.floor(xyz[:, 0] / 20).astype(np.int64) << 32) + np.floor(xyz[:, 1] / 20).astype(
            np.int64
        )
        order = np.argsort(keys, kind="stable")
        return keys[order], xyz[order], data["intensity"][order]

    def write(cell: tuple[int, list[tuple[Any, Any]]]) -> int:
        key, parts = cell
        xyz = np.concatenate([p for p, _ in parts])
        intensity = np.concatenate([i for _, i in parts])
        record = np.zeros((len(xyz), record_bytes), np.uint8)
        ints = np.round((xyz - np.floor(xyz.min(axis=0))) / 0.001).astype(np.int32)
        record[:, :12] = ints.view(np.uint8).reshape(len(xyz), 12)
        record[:, 12:14] = intensity.astype(np.uint16).view(np.uint8).reshape(len(xyz), 2)
        with open(out / f"{key}.bin", "wb") as stream:
            stream.write(record.data)
            stream.flush()
            os.fsync(stream.fileno())
        return len(xyz)

    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    t0 = time.perf_counter()
    cells: dict[int, list[tuple[Any, Any]]] = {}
    with threadpool_limits(1), ThreadPoolExecutor(2) as pool:
        for keys, xyz, intensity in pool.map(load, items):
            starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
            ends = np.r_[starts[1:], len(keys)]
            for k, a, b in zip(keys[starts].tolist(), starts, ends, strict=True):
                cells.setdefault(k, []).append((xyz[a:b], intensity[a:b]))
        points = sum(pool.map(write, sorted(cells.items())))
    fd = os.open(out, os.O_RDONLY)
    os.fsync(fd)
    os.close(fd)
    seconds = time.perf_counter() - t0
    return {"seconds": seconds, "points": points, "tiles": len(cells)}


def _child(args: list[str]) -> None:
    kind, *rest = args
    if kind == "simulate":
        result = measure_simulate(Path(rest[0]), int(rest[1]), float(rest[2]))
    elif kind == "tile":
        result = measure_tile(Path(rest[0]), Path(rest[1]), rest[2] == "laz", rest[3:] == ["warm"])
    elif kind == "workers":
        result = measure_tile_workers(Path(rest[0]), Path(rest[1]), int(rest[2]))
    elif kind == "baseline":
        result = measure_baseline_files(Path(rest[0]), Path(rest[1]), Path(rest[2]))
    elif kind == "floor":
        result = measure_floor(Path(rest[0]), Path(rest[1]), Path(rest[2]))
    elif kind == "copy":
        result = measure_copy(Path(rest[0]), Path(rest[1]), rest[2] == "laz")
    else:
        raise SystemExit(f"unknown measurement {kind}")
    print(json.dumps({**result, **_peak_mb()}))


CHILD_ENV: dict[str, str] = {}


def run_child(*args: str) -> dict[str, Any]:
    """One measurement in its own process, started with no dirty pages left by the last one
    (``sync``, not timed): writes still in flight would slow whichever runs next."""
    os.sync()
    out = subprocess.run(
        [sys.executable, __file__, "--child", *args],
        check=True,
        capture_output=True,
        text=True,
        env={**os.environ, **CHILD_ENV},
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def best_of(repeat: int, *args: str) -> dict[str, Any]:
    """The fastest of ``repeat`` child runs (each its own process), with the largest peak."""
    runs = [run_child(*args) for _ in range(max(1, repeat))]
    best = min(runs, key=lambda r: r["seconds"])
    return {**best, "peak_mb": max(r["peak_mb"] for r in runs), "runs": len(runs)}


# --- the run -----------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20_000_000)
    parser.add_argument("--area", type=float, default=200.0)
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--keep", action="store_true", help="keep the work folder")
    parser.add_argument("--blas-threads", type=int, default=None)
    parser.add_argument("--repeat", type=int, default=1, help="best of N runs per measurement")
    parser.add_argument("--workers", default=None, help="also tile on LocalClusters: 1,2")
    parser.add_argument("--no-copy", action="store_true", help="skip tile vs copy")
    parser.add_argument(
        "--warm",
        action="store_true",
        help="time tile in a process that has tiled the bundled demo mission first",
    )
    parser.add_argument(
        "--fixed-cost",
        action="store_true",
        help="only the fixed cost of a small job: tile a tiny mission vs interpreter start",
    )
    parser.add_argument("--tiny-points", type=int, default=5000)
    parser.add_argument("--child", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args.child)
        return
    if args.fixed_cost:
        fixed_cost(args)
        return

    if args.blas_threads is not None:
        for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            CHILD_ENV[name] = str(args.blas_threads)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_tile_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        existing = sorted((work / "sim" / "missions").glob("*"))
        if existing:
            sim = {"mission": str(existing[0])}
            print(f"mission: reusing {existing[0]}", flush=True)
        else:
            sim = run_child("simulate", str(work / "sim"), str(args.points), str(args.area))
            print(
                f"mission: {sim['points']:,} points in {sim['payloads']} payloads "
                f"(simulated in {sim['seconds']:.1f} s)",
                flush=True,
            )
        if not args.no_copy:
            tile_versus_copy(args, sim, work)
        if args.workers:
            tile_on_workers(args, sim, work, [int(n) for n in args.workers.split(",")])
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


def tile_on_workers(args: Any, sim: dict[str, Any], work: Path, counts: list[int]) -> None:
    runs = {}
    for n in counts:
        runs[n] = best_of(
            args.repeat, "workers", sim["mission"], str(work / "catalog_dask"), str(n)
        )
        r = runs[n]
        print(
            f"tile laz on {n} worker(s): {r['seconds']:.2f} s "
            f"({r['points'] / r['seconds'] / 1e6:.3f} Mpts/s; cluster start "
            f"{r['startup_seconds']:.1f} s, client peak {r['peak_mb']:.0f} MB)",
            flush=True,
        )
    first, last = counts[0], counts[-1]
    speedup = runs[first]["seconds"] / runs[last]["seconds"]
    verdict = "ok" if speedup >= TARGET_SPEEDUP else f"below the {TARGET_SPEEDUP} target"
    print(f"speed-up {first} -> {last} workers: {speedup:.2f}x  ({verdict})")


def tile_versus_copy(args: Any, sim: dict[str, Any], work: Path) -> None:
    results: dict[str, dict[str, Any]] = {}
    for fmt in ("laz", "las"):
        warm = ["warm"] if args.warm else []
        results[f"tile {fmt}"] = best_of(
            args.repeat, "tile", sim["mission"], str(work / f"catalog_{fmt}"), fmt, *warm
        )
        print(f"tile {fmt}: {results[f'tile {fmt}']}", flush=True)
    run_child("baseline", str(work / "catalog_las"), str(work / "all.las"), str(work / "all.laz"))
    for fmt in ("laz", "las"):
        results[f"copy {fmt}"] = best_of(
            args.repeat, "copy", str(work / f"all.{fmt}"), str(work / f"copy.{fmt}"), fmt
        )
        print(f"copy {fmt}: {results[f'copy {fmt}']}", flush=True)
    results["floor las"] = best_of(
        args.repeat, "floor", sim["mission"], str(work / "catalog_las"), str(work / "floor")
    )
    print(f"floor las: {results['floor las']}", flush=True)

    print(f"\n{'measurement':<10} {'points':>12} {'seconds':>8} {'Mpts/s':>8} {'peak MB':>8}")
    for name, r in results.items():
        pps = r["points"] / r["seconds"]
        print(
            f"{name:<10} {r['points']:>12,} {r['seconds']:>8.2f} {pps / 1e6:>8.3f} "
            f"{r['peak_mb']:>8.0f}"
        )
    for fmt in ("laz", "las"):
        tile, copy = results[f"tile {fmt}"], results[f"copy {fmt}"]
        ratio = (tile["points"] / tile["seconds"]) / (copy["points"] / copy["seconds"])
        verdict = "ok" if ratio >= TARGET_RATIO else f"below the {TARGET_RATIO} target"
        print(f"throughput ratio tile/copy ({fmt.upper()}): {ratio:.2f}  ({verdict})")
    floor, copy = results["floor las"], results["copy las"]
    print(
        f"floor (least any tiler does, LAS) / copy: {copy['seconds'] / floor['seconds']:.2f}; "
        f"tile / floor: {floor['seconds'] / results['tile las']['seconds']:.2f}"
    )


# --- the fixed cost of a small job ------------------------------------------------------------

_TILE_CODE = """
import sys
from standgrid.cli import cli
try:
    cli(sys.argv[1:], prog_name="standgrid")
except SystemExit as exc:
    if exc.code:
        raise
heavy = [m for m in {heavy!r} if m in sys.modules]
print("loaded: " + ",".join(heavy), file=sys.stderr)
"""


def cpu_of(argv: list[str], env: dict[str, str]) -> dict[str, Any]:
    """CPU seconds (user + sys, the process and its children) and wall seconds of one run."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    assert proc.stderr is not None
    err = proc.stderr.read().decode(errors="replace")
    _pid, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"{' '.join(argv)} failed ({proc.returncode}):\n{err}")
    loaded = [line for line in err.splitlines() if line.startswith("loaded: ")]
    return {
        "cpu": usage.ru_utime + usage.ru_stime,
        "wall": wall,
        "loaded": loaded[-1].removeprefix("loaded: ") if loaded else "",
    }


def fixed_cost(args: Any) -> None:
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_fixed_"))
    work.mkdir(parents=True, exist_ok=True)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPYCACHEPREFIX"] = str(work / "pycache")
    try:
        missions = sorted((work / "sim" / "missions").glob("*"))
        if not missions:
            from standgrid.simulate import simulate_mission

            simulate_mission(
                work / "sim",
                seed=SEED,
                area=40.0,
                points_per_payload=max(50, args.tiny_points // 8),
            )
            missions = sorted((work / "sim" / "missions").glob("*"))
        mission = missions[0]
        code = _TILE_CODE.format(heavy=HEAVY_MODULES)

        def tile_argv(n: int) -> list[str]:
            out = work / f"catalog_{n}"
            shutil.rmtree(out, ignore_errors=True)
            return [sys.executable, "-c", code, "tile", str(mission), "-o", str(out)]

        runs = {
            "python -c pass": lambda n: [sys.executable, "-c", "pass"],
            "import standgrid.cli": lambda n: [sys.executable, "-c", "import standgrid.cli"],
            "standgrid tile (tiny)": tile_argv,
        }
        for make in runs.values():  # warm the bytecode cache and the page cache
            cpu_of(make(0), env)
        best: dict[str, dict[str, Any]] = {}
        for n in range(max(3, args.repeat)):
            for name, make in runs.items():
                os.sync()
                r = cpu_of(make(n), env)
                if name not in best or r["cpu"] < best[name]["cpu"]:
                    best[name] = r
        import laspy

        points = sum(
            laspy.read(p).header.point_count for p in (work / "catalog_0").glob("tiles/*/*.la[sz]")
        )
        print(f"tiny mission: {mission.name}, {points:,} points tiled")
        base = best["python -c pass"]["cpu"]
        print(
            f"{'run (best of ' + str(max(3, args.repeat)) + ')':<24} {'CPU s':>7} {'wall s':>7} "
            f"{'x start':>8}"
        )
        for name, r in best.items():
            print(f"{name:<24} {r['cpu']:>7.3f} {r['wall']:>7.3f} {r['cpu'] / base:>8.1f}")
        tile = best["standgrid tile (tiny)"]
        print(
            f"fixed cost of a tiny tile (CPU s above interpreter start): {tile['cpu'] - base:.3f}"
        )
        print(f"heavy modules the tile command loaded: {tile['loaded'] or 'none'}")
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
