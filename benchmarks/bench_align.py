"""What alignment adds to tiling: two overlapping missions under a canopy, tiled with and
without alignment, alternated, each run in its own process.

Usage::

    python benchmarks/bench_align.py [--points-per-payload 150000] [--area 60]
                                     [--workdir DIR] [--repeat 2]

Simulates (once; reused from ``--workdir``) robot A's and robot B's missions of one day
over a mixed stand (handheld ray-casting scanner, canopy GNSS), about 2 M points each, then
tiles both into a fresh catalog ``--repeat`` times each way, alternating: ``--no-align``
(the baseline, measured in the same run) and aligned (landmarks, registration, graph,
refit; no landmark cache: each run is a fresh catalog in a fresh process). Prints wall
time, CPU time and peak RSS of each, and the ratios aligned / baseline.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

CHILD = """
import json, resource, sys, time
from pathlib import Path
from standgrid.pipeline.tile import tile_missions
from standgrid.tiling.options import TileOptions
missions, out, align = json.loads(sys.argv[1])
t0, c0 = time.perf_counter(), time.process_time()
report = tile_missions([Path(m) for m in missions], out, TileOptions(overwrite=True, align=align))
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"wall": wall, "cpu": cpu, "peak_mb": peak, "points": report.points_out}))
"""


def _run(missions: list[Path], out: Path, align: bool) -> dict[str, float]:
    done = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps([[str(m) for m in missions], str(out), align])],
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--points-per-payload", type=int, default=150_000)
    parser.add_argument("--area", type=float, default=60.0)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/standgrid-bench-align"))
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()

    from standgrid.simulate import simulate_mission
    from standgrid.simulate.gnss import GnssModel

    root = args.workdir
    missions_dir = root / "missions"
    if not missions_dir.is_dir() or len(list(missions_dir.iterdir())) < 2:
        t0 = time.perf_counter()
        for epoch in (1, 3):
            simulate_mission(
                root,
                seed=7,
                epoch=epoch,
                overwrite=True,
                area=args.area,
                forest="mixed",
                scanner_kind="handheld",
                lane_spacing=15.0,
                points_per_payload=args.points_per_payload,
                gnss=GnssModel.under_canopy(),
            )
        print(f"simulated in {time.perf_counter() - t0:.0f} s")
    missions = sorted(missions_dir.iterdir())
    runs: dict[bool, list[dict[str, float]]] = {False: [], True: []}
    for k in range(args.repeat):
        for align in (False, True):
            out = root / f"catalog_{align}_{k}"
            runs[align].append(_run(missions, out, align))
            shutil.rmtree(out, ignore_errors=True)
    points = runs[False][0]["points"]
    print(f"{len(missions)} missions, {points:,.0f} points; {args.repeat} runs each, alternated")
    best = {}
    for align, label in ((False, "GNSS only (--no-align)"), (True, "aligned")):
        r = min(runs[align], key=lambda x: x["wall"])
        best[align] = r
        print(
            f"{label:24s} wall {r['wall']:6.1f} s  cpu {r['cpu']:6.1f} s  "
            f"peak {r['peak_mb']:6.0f} MB  ({points / r['wall'] / 1e6:.2f} M pts/s)"
        )
    a, b = best[True], best[False]
    added = a["wall"] - b["wall"]
    print(
        f"aligned / GNSS only: wall {a['wall'] / b['wall']:.2f}x (+{added:.1f} s), "
        f"cpu {a['cpu'] / b['cpu']:.2f}x, peak {a['peak_mb'] / b['peak_mb']:.2f}x "
        f"(+{a['peak_mb'] - b['peak_mb']:.0f} MB)"
    )
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"this process's peak: {own:.0f} MB")


if __name__ == "__main__":
    main()
