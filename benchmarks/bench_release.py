"""The same CLI commands with this checkout and with another standgrid install, same run.

Where PDAL cannot be built (not in Debian bookworm, no PyPI wheel), issue 22 asks for the
same commands against the previous release. Install that release in its own venv, e.g.::

    git worktree add --detach /work/prev d608f6a
    python3 -m venv /work/venv-prev && /work/venv-prev/bin/pip install /work/prev
    python benchmarks/bench_release.py --other /work/venv-prev/bin/standgrid \
        [--points 2000000,20000000] [--memory 512] [--repeat 1] [--workdir DIR]

For each size it simulates one mission (reused from ``--workdir``), then runs, A/B
alternated (other first, then this), each command in a fresh process: ``tile`` to LAZ,
``tile --las``, and ``enrich --memory M`` of the LAZ catalog. Prints the CPU seconds of the
whole process tree (user + system, from the kernel's accounting of waited-for children),
the wall time and the peak RSS of each, the ratio this / other, and whether the peak keeps
to the budget (issue 22: peak <= 1.1 x budget + the interpreter, about 150-200 MB). Checks
that both give the same points per tile. A shared machine inflates both sides alike.
"""

from __future__ import annotations

import argparse
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


def run_measured(cmd: list[str]) -> dict[str, float]:
    """Run ``cmd`` to completion; its CPU seconds (tree), wall seconds and peak RSS (MB)."""
    subprocess.run(["sync"], check=False)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    stderr = proc.stderr.read() if proc.stderr else ""
    if proc.stderr:
        proc.stderr.close()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{stderr[-2000:]}")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"cpu": cpu, "wall": wall, "peak_mb": usage.ru_maxrss / 1024}


def tile_points(catalog: Path) -> dict[str, int]:
    import laspy

    counts = {}
    for path in sorted((catalog / "tiles").rglob("*.la[sz]")):
        with laspy.open(path) as reader:
            counts[path.relative_to(catalog).as_posix()] = int(reader.header.point_count)
    return counts


def interpreter_mb() -> float:
    """Peak RSS of a process that imports what tiling and enrichment import."""
    code = (
        "import standgrid.pipeline.tile, standgrid.pipeline.enrich, laspy, scipy.spatial, "
        "geopandas, pyogrio, rasterio\n"
        "print(open('/proc/self/status').read())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout
    for line in out.splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--other", required=True, help="the other install's standgrid script")
    parser.add_argument("--this", default=str(Path(sys.executable).with_name("standgrid")))
    parser.add_argument("--points", default="2000000,20000000")
    parser.add_argument("--area", type=float, default=200.0)
    parser.add_argument("--memory", type=int, default=512, help="MB, for tile and enrich")
    parser.add_argument("--repeat", type=int, default=1, help="best of N per measurement")
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--skip-enrich", action="store_true")
    parser.add_argument(
        "--skip-tile", action="store_true", help="enrich the LAZ catalogs already in --workdir"
    )
    opts = parser.parse_args(argv)
    from bench_tile import measure_simulate

    work = opts.workdir or Path(tempfile.mkdtemp(prefix="standgrid-bench-release-"))
    work.mkdir(parents=True, exist_ok=True)
    sides = {"other": opts.other, "this": opts.this}
    interp = interpreter_mb()
    print(f"interpreter (imports only): {interp:.0f} MB; budget {opts.memory} MB")
    rows: list[tuple[str, dict[str, Any]]] = []
    for n in (int(p) for p in opts.points.split(",")):
        sim_root = work / f"sim-{n}"
        missions = list((sim_root / "missions").glob("*")) if sim_root.exists() else []
        if not missions:
            shutil.rmtree(sim_root, ignore_errors=True)
            measure_simulate(sim_root, n, opts.area)
            missions = list((sim_root / "missions").glob("*"))
        mission = missions[0]
        label = f"{n / 1e6:g} M"
        for what, extra in () if opts.skip_tile else (("tile LAZ", []), ("tile LAS", ["--las"])):
            best: dict[str, dict[str, float]] = {}
            counts = {}
            for _ in range(opts.repeat):
                for side, exe in sides.items():
                    cat = work / f"cat-{side}-{n}-{'las' if extra else 'laz'}"
                    cmd = [exe, "tile", str(mission), "-o", str(cat), "--overwrite"]
                    cmd += ["--memory", str(opts.memory), *extra]
                    got = run_measured(cmd)
                    if side not in best or got["cpu"] < best[side]["cpu"]:
                        best[side] = got
                    counts[side] = tile_points(cat)
            if counts["this"] != counts["other"]:
                print(f"  !! {what} {label}: the two give different points per tile")
            rows.append((f"{what}, {label}", best))
        if opts.skip_enrich:
            continue
        best = {}
        for _ in range(opts.repeat):
            for side, exe in sides.items():
                src = work / f"cat-{side}-{n}-laz"
                cat = work / f"enr-{side}-{n}"
                shutil.rmtree(cat, ignore_errors=True)
                shutil.copytree(src, cat)
                got = run_measured([exe, "enrich", str(cat), "--memory", str(opts.memory)])
                if side not in best or got["cpu"] < best[side]["cpu"]:
                    best[side] = got
        rows.append((f"enrich, {label}", best))

    print()
    print(
        "| work | this: CPU s | peak MB | other: CPU s | peak MB | CPU this/other | "
        f"peak - interp <= 1.1 x {opts.memory}? |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, best in rows:
        a, b = best["this"], best["other"]
        keeps = "yes" if a["peak_mb"] - interp <= 1.1 * opts.memory else "NO"
        print(
            f"| {name} | {a['cpu']:.1f} | {a['peak_mb']:.0f} | {b['cpu']:.1f} | "
            f"{b['peak_mb']:.0f} | {a['cpu'] / b['cpu']:.2f} | {keeps} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
