"""Tile one big plain scan (a LAZ file as a commercial scanner delivers it); print CPU, wall,
peak RSS against the memory budget, and a baseline measured in the same run.

    python benchmarks/bench_scan.py [--points 20000000] [--budget-mb 512] [--workdir DIR]

The scan is written once (a forest-like cloud over 400 x 400 m, LAS 1.4 format 6, EPSG:32632,
adjusted standard GPS time). Each measurement runs in a fresh child process, so its peak RSS
(``ru_maxrss`` of the child) is its own:

- baseline: ``laspy`` reads the file in chunks of 1 M points and writes them to one LAZ
  (the least any tiler must do: decompress every point, compress every point);
- ``standgrid tile SCAN.laz --memory BUDGET`` into a new catalog (20 m stand grid, LAZ).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

_CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    start = time.perf_counter()
    exec(sys.argv[1])
    usage = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(json.dumps({
        "wall_s": time.perf_counter() - start,
        "cpu_s": usage.ru_utime + usage.ru_stime + kids.ru_utime + kids.ru_stime,
        "peak_mb": max(usage.ru_maxrss, kids.ru_maxrss) / 1024,
    }))
    """
)


def _measure(code: str) -> dict[str, float]:
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, code], capture_output=True, text=True, check=False
    )
    if done.returncode:
        raise SystemExit(done.stderr[-3000:])
    result: dict[str, float] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def _write_scan(path: Path, points: int) -> None:
    import laspy
    import numpy as np
    import pyproj

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = [0.001] * 3
    header.offsets = [500_000.0, 5_200_000.0, 0.0]
    header.add_crs(pyproj.CRS.from_epsg(32632))
    header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    rng = np.random.default_rng(1)
    with laspy.open(path, mode="w", header=header) as writer:
        step = 2_000_000
        for start in range(0, points, step):
            n = min(step, points - start)
            las = laspy.ScaleAwarePointRecord.zeros(n, header=header)
            las.x = 500_000.0 + rng.uniform(0, 400, n)
            las.y = 5_200_000.0 + rng.uniform(0, 400, n)
            las.z = 300.0 + rng.gamma(2.0, 4.0, n)
            las.intensity = rng.integers(0, 4000, n)
            las.gps_time = 370_736_018.0 + (start + np.arange(n)) * 1e-5
            writer.write_points(las)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--points", type=int, default=20_000_000)
    parser.add_argument("--budget-mb", type=int, default=512)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/standgrid-bench-scan"))
    args = parser.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    scan = args.workdir / f"scan_{args.points}.laz"
    if not scan.exists():
        start = time.perf_counter()
        _write_scan(scan, args.points)
        print(f"wrote {scan} in {time.perf_counter() - start:.0f} s", flush=True)
    copy = args.workdir / "copy.laz"
    catalog = args.workdir / "catalog"
    shutil.rmtree(catalog, ignore_errors=True)
    base = _measure(
        "import laspy\n"
        f"with laspy.open({str(scan)!r}) as r, laspy.open({str(copy)!r}, mode='w', "
        "header=r.header) as w:\n"
        "    for p in r.chunk_iterator(1_000_000): w.write_points(p)"
    )
    tiled = _measure(
        "from standgrid.cli import cli\n"
        f"cli([ 'tile', {str(scan)!r}, '-o', {str(catalog)!r}, '--memory', "
        f"'{args.budget_mb}', '-q', '--json'], standalone_mode=False)"
    )
    print(
        f"{args.points:,} points, LAZ {scan.stat().st_size / 1e6:.0f} MB, budget "
        f"{args.budget_mb} MB"
    )
    for name, m in (("laspy read + write (baseline)", base), ("standgrid tile", tiled)):
        print(
            f"{name:32s} wall {m['wall_s']:6.1f} s  CPU {m['cpu_s']:6.1f} s  "
            f"peak RSS {m['peak_mb']:6.0f} MB"
        )
    print(
        f"ratio tile / baseline: CPU {tiled['cpu_s'] / base['cpu_s']:.2f}x, "
        f"peak RSS {tiled['peak_mb'] / base['peak_mb']:.2f}x; "
        f"peak / budget {tiled['peak_mb'] / args.budget_mb:.2f}"
    )


if __name__ == "__main__":
    main()
