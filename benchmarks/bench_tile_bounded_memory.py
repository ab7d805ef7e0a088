"""Tile a mission far larger than the memory budget; print peak RSS against the budget.

    python benchmarks/bench_tile_bounded_memory.py [--points 20000000] [--area 200]
        [--budget-mb 512,2048] [--workers 0] [--workdir /tmp/standgrid-bounded]

The mission is simulated once (``bench_tile.measure_simulate``: about ``--points`` points
over ``--area`` metres; reused from ``--workdir``). Each measurement runs in a fresh child
process, so its peak RSS (``ru_maxrss``; with ``--workers N``, each dask worker's too) is its
own:

- baseline: a child that imports what tiling imports and does nothing (the interpreter);
- ``tile_missions`` with ``--memory BUDGET`` (one process, or a LocalCluster of N workers).

Prints, per budget, peak / budget and whether ``peak - baseline <= 1.1 x budget`` (the
target of issue 22: the whole process stays within its budget plus the interpreter).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]

_CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    sys.path.insert(0, {bench!r})
    start = time.perf_counter()
    out = {{}}
    exec(sys.argv[1])
    usage = resource.getrusage(resource.RUSAGE_SELF)
    out.update(seconds=time.perf_counter() - start,
               cpu_s=usage.ru_utime + usage.ru_stime,
               peak_mb=usage.ru_maxrss / 1024)
    print(json.dumps(out))
    """
).format(bench=str(REPO / "benchmarks"))

_IMPORTS = (
    "import numpy, laspy, pyproj, shapely\n"
    "import standgrid.pipeline.tile, standgrid.partition.engine, standgrid.tiling.cell_task\n"
)


def _measure(code: str) -> dict[str, Any]:
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, code], capture_output=True, text=True, check=False
    )
    if done.returncode:
        raise SystemExit(done.stderr[-3000:])
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def _tile_code(mission: Path, catalog: Path, budget_mb: int, workers: int) -> str:
    return _IMPORTS + textwrap.dedent(
        f"""
        from standgrid.engine import Execution, open_executor
        from standgrid.pipeline.tile import tile_missions
        from standgrid.tiling.options import TileOptions
        execution = Execution(memory_mb={budget_mb})
        options = TileOptions(overwrite=True)
        workers = {workers} or None
        def _peak():
            import resource
            return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        with open_executor(workers, memory_budget=execution.memory_budget.bytes) as executor:
            report = tile_missions([{str(mission)!r}], {str(catalog)!r}, options,
                                   execution=execution.on(executor))
            client = getattr(executor, "client", None)
            if client is not None:
                out["worker_peaks_mb"] = sorted(client.run(_peak).values())
        assert report.points_in == report.points_out
        epoch = next(iter(report.epochs.values()))
        out.update(points=report.points_out, cells=epoch["cells"],
                   spilled_mb=epoch["bytes_spilled"] / 2**20)
        """
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--points", type=int, default=20_000_000)
    parser.add_argument("--area", type=float, default=200.0)
    parser.add_argument("--budget-mb", default="512,2048", help="comma-separated, MB")
    parser.add_argument("--workers", type=int, default=0, help="0 = this process")
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/standgrid-bounded"))
    args = parser.parse_args()

    sim = args.workdir / f"sim-{args.points}"
    if not (sim / "missions").exists():
        made = _measure(
            "from bench_tile import measure_simulate\n"
            f"out.update(measure_simulate(__import__('pathlib').Path({str(sim)!r}), "
            f"{args.points}, {args.area}))"
        )
        print(f"simulated {made['points']:,} points in {made['seconds']:.0f} s", flush=True)
    mission = next((sim / "missions").iterdir())
    base = _measure(_IMPORTS)
    print(f"baseline (interpreter + imports): peak RSS {base['peak_mb']:.0f} MB", flush=True)
    for budget in (int(b) for b in args.budget_mb.split(",")):
        catalog = args.workdir / "catalog"
        shutil.rmtree(catalog, ignore_errors=True)
        m = _measure(_tile_code(mission, catalog, budget, args.workers))
        shutil.rmtree(catalog, ignore_errors=True)
        peaks = [m["peak_mb"], *m.get("worker_peaks_mb", [])]
        where = "this process" if not args.workers else f"{args.workers} workers"
        print(
            f"tile {m['points']:,} points ({where}), --memory {budget}: {m['seconds']:.1f} s, "
            f"{m['cells']} tiles, spilled {m['spilled_mb']:,.0f} MB"
        )
        for name, peak in zip(["process", *(f"worker {k}" for k in range(9))], peaks, strict=False):
            ok = peak - base["peak_mb"] <= 1.1 * budget
            print(
                f"  {name:10s} peak RSS {peak:6.0f} MB  peak / budget {peak / budget:.2f}  "
                f"peak - baseline {peak - base['peak_mb']:6.0f} MB <= 1.1 x budget "
                f"({1.1 * budget:.0f} MB)? {'yes' if ok else 'NO'}",
                flush=True,
            )


if __name__ == "__main__":
    main()
