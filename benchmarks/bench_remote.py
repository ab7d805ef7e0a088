"""Tile and enrich with the catalog on a local S3-compatible server, beside the same on disk.

Usage::

    python benchmarks/bench_remote.py [--points 2000000] [--area 100] [--repeat 1]
                                      [--workdir DIR] [--keep] [--no-enrich]

1. Simulates one mission of about ``--points`` points (as ``bench_tile.py`` does).
2. Starts ``moto_server`` on 127.0.0.1 (the server the tests use).
3. Alternating disk and S3 (``--repeat`` rounds; the machine may be shared):
   ``standgrid tile MISSION -o DISK`` and ``-o s3://bucket/cat``, then ``standgrid enrich``
   of each. Every command runs in its own process; its wall time and its CPU seconds
   (the process tree's) are measured.
4. Prints each, and the ratio S3 / disk (best of the rounds), and what the S3 catalog
   costs in transfers: the bytes of the catalog (uploaded once per commit; enrich
   downloads it first).

moto_server keeps objects in its own memory: it stands for the protocol (requests,
multipart uploads, conditional writes), not for a network: the S3 figures are the client's
own cost of object storage, not a cloud's latency or bandwidth.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.s3_server import CREDENTIALS, moto_server, new_bucket

SEED = 7


def simulate(root: Path, points: int, area: float) -> Path:
    from standgrid.simulate import SimulationConfig, simulate_mission
    from standgrid.simulate.mission import run_simulation

    spans = len(run_simulation(SEED, 1, SimulationConfig(area=area)).spans)
    per_payload = max(1000, math.ceil(points / spans / 0.985))
    sim = simulate_mission(root, seed=SEED, area=area, points_per_payload=per_payload)
    print(f"simulated {sim.n_points:,} points in {len(sim.spans)} payloads", flush=True)
    return Path(sim.mission_dir)


def timed(argv: list[str], env: dict[str, str]) -> dict[str, float]:
    """Wall and CPU seconds (this child and its children) of one command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(argv, env=env, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall": wall, "cpu": cpu}


def size_of(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--points", type=int, default=2_000_000)
    parser.add_argument("--area", type=float, default=100.0)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--keep", action="store_true")
    parser.add_argument("--no-enrich", action="store_true")
    args = parser.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench-remote-"))
    work.mkdir(parents=True, exist_ok=True)
    exe = str(Path(sys.executable).with_name("standgrid"))
    try:
        mission = simulate(work / "sim", args.points, args.area)
        with moto_server() as endpoint:
            env = {**os.environ, **CREDENTIALS, "AWS_ENDPOINT_URL": endpoint}
            env["STANDGRID_WORK_DIR"] = str(work / "s3-work")
            best: dict[str, dict[str, float]] = {}
            disk_bytes = 0
            for round_ in range(args.repeat):
                os.environ.update(CREDENTIALS)
                bucket = new_bucket(endpoint)
                disk = work / f"disk-{round_}" / "cat"
                s3 = f"s3://{bucket}/cat"
                steps = [("tile", [exe, "tile", str(mission), "-q", "-o"])]
                if not args.no_enrich:
                    steps.append(("enrich", [exe, "enrich", "-q"]))
                for name, argv in steps:
                    for where, target in (("disk", str(disk)), ("s3", s3)):
                        subprocess.run(["sync"], check=False)
                        got = timed([*argv, target], env)
                        key = f"{name} {where}"
                        if key not in best or got["cpu"] < best[key]["cpu"]:
                            best[key] = got
                        print(
                            f"round {round_ + 1}: {key}: {got['wall']:.2f} s wall, "
                            f"{got['cpu']:.2f} CPU s",
                            flush=True,
                        )
                disk_bytes = size_of(disk)
                shutil.rmtree(disk.parent, ignore_errors=True)
            print(f"\ncatalog: {disk_bytes / 1e6:.1f} MB ({args.points:,} points)")
            for name, _ in steps:
                d, s = best[f"{name} disk"], best[f"{name} s3"]
                print(
                    f"{name:6}  disk {d['wall']:7.2f} s wall {d['cpu']:7.2f} CPU s | "
                    f"S3 {s['wall']:7.2f} s wall {s['cpu']:7.2f} CPU s | "
                    f"S3/disk: wall {s['wall'] / d['wall']:.2f}x, CPU {s['cpu'] / d['cpu']:.2f}x"
                )
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
