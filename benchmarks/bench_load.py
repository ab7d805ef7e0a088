"""Enrich's CPU time on an idle machine against the same enrich under load, same run.

Usage::

    python benchmarks/bench_load.py [--spinners 4] [--repeat 1] [--workdir DIR] [--keep]
                                    [--env NAME=VALUE ...] [--workers N]

1. Tiles the bundled missions (``data/missions``) into a catalog once (not timed).
2. Enriches a fresh copy of it with ``standgrid enrich`` in a child process, idle: the
   child's CPU seconds (user + sys of it and its children, from ``wait4``: what
   ``RUSAGE_CHILDREN`` counts) and wall seconds.
3. Starts ``--spinners`` busy processes (pure-Python spin loops; by default twice the
   cores), enriches another fresh copy the same way, stops the spinners.

Prints both and the ratio loaded / idle of enrich's CPU seconds (target <= 1.3: threads
that wait for work must sleep, not spin, when the cores are shared; a ratio far above it
is OpenMP or BLAS threads spin-waiting while the other processes hold the cores). The wall
time under load is longer by nature (the cores are shared); only the CPU time is judged.

``--env NAME=VALUE`` sets a variable in the enrich child (e.g. ``OMP_WAIT_POLICY=ACTIVE
OPENBLAS_THREAD_TIMEOUT=28 GOMP_SPINCOUNT=30000000000`` asks for the spinning threads back,
as a same-run baseline; standgrid never overrides a setting given explicitly).
``--repeat N`` keeps the least CPU of N runs per condition.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
TARGET_RATIO = 1.3
SPIN = "while True:\n    pass\n"
CLI = "import sys\nfrom standgrid.cli import cli\ncli(sys.argv[1:], prog_name='standgrid')\n"


def run_measured(argv: list[str], env: dict[str, str]) -> dict[str, float]:
    """Run ``argv``; its CPU seconds (it and the children it waited for) and wall seconds."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    assert proc.stderr is not None
    err = proc.stderr.read().decode(errors="replace")
    _pid, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = code = os.waitstatus_to_exitcode(status)
    if code:
        raise SystemExit(f"{' '.join(argv[:4])} ... failed ({code}):\n{err[-3000:]}")
    return {
        "cpu": usage.ru_utime + usage.ru_stime,
        "user": usage.ru_utime,
        "sys": usage.ru_stime,
        "wall": wall,
    }


class Load:
    """``count`` busy processes (pure-Python spin loops) for the duration of a with-block."""

    def __init__(self, count: int) -> None:
        self.count = count
        self.procs: list[subprocess.Popen[bytes]] = []

    def __enter__(self) -> Load:
        for _ in range(self.count):
            self.procs.append(subprocess.Popen([sys.executable, "-c", SPIN]))
        time.sleep(1.0)  # let the load settle (the load average is not needed)
        return self

    def __exit__(self, *exc: object) -> None:
        for proc in self.procs:  # only the processes started here, by their handles
            proc.kill()
        for proc in self.procs:
            proc.wait()
        self.procs.clear()


def enrich_once(
    tiled: Path, work: Path, name: str, env: dict[str, str], extra: list[str]
) -> dict[str, float]:
    copy = work / f"catalog_{name}"
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(tiled, copy, symlinks=True)
    os.sync()
    try:
        return run_measured([sys.executable, "-c", CLI, "enrich", str(copy), "-q", *extra], env)
    finally:
        shutil.rmtree(copy, ignore_errors=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spinners", type=int, default=2 * (os.cpu_count() or 1))
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--keep", action="store_true")
    parser.add_argument("--missions", type=Path, default=REPO / "data" / "missions")
    parser.add_argument("--workers", type=int, default=None, help="enrich --workers N")
    parser.add_argument("--env", nargs="*", default=[], metavar="NAME=VALUE")
    args = parser.parse_args()

    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_load_"))
    work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    for item in args.env:
        key, _, value = item.partition("=")
        env[key] = value
    extra = ["--workers", str(args.workers)] if args.workers else []
    try:
        tiled = work / "tiled"
        if not (tiled / "catalog.json").is_file():
            missions = sorted(p for p in args.missions.iterdir() if p.is_dir())
            argv = [
                sys.executable,
                "-c",
                CLI,
                "tile",
                *map(str, missions),
                "-o",
                str(tiled),
                "-q",
                "--overwrite",
            ]
            subprocess.run(argv, check=True, env=dict(os.environ))
        results: dict[str, dict[str, Any]] = {}
        for _ in range(max(1, args.repeat)):
            idle = enrich_once(tiled, work, "idle", env, extra)
            with Load(args.spinners):
                loaded = enrich_once(tiled, work, "load", env, extra)
            for name, r in (("idle", idle), (f"load ({args.spinners} spinners)", loaded)):
                if name not in results or r["cpu"] < results[name]["cpu"]:
                    results[name] = r
        print(f"enrich of {tiled.name} ({os.cpu_count()} cores); env: {' '.join(args.env) or '-'}")
        print(f"{'condition':<22} {'CPU s':>8} {'user s':>8} {'sys s':>7} {'wall s':>8}")
        for name, r in results.items():
            print(
                f"{name:<22} {r['cpu']:>8.2f} {r['user']:>8.2f} {r['sys']:>7.2f} {r['wall']:>8.2f}"
            )
        idle_cpu, load_cpu = (r["cpu"] for r in results.values())
        ratio = load_cpu / idle_cpu
        verdict = "ok" if ratio <= TARGET_RATIO else f"above the {TARGET_RATIO} target"
        print(f"CPU ratio load / idle: {ratio:.2f}  ({verdict})")
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
