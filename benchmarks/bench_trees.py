"""``segment_trees`` of this tree against a baseline revision, on the chunks of a real epoch.

Usage::

    python benchmarks/bench_trees.py CATALOG --baseline REV [--workdir DIR] [--same]

1. Enriches a copy of the tiled ``CATALOG`` (``enrich_catalog``, one process) and keeps the
   inputs of every chunk's ``segment_trees`` call (points, heights above ground, keywords)
   in ``--workdir`` (reused when present).
2. Runs the baseline's ``segment_trees`` (the ``standgrid`` package of ``git archive REV``,
   in a subprocess) and this tree's on each chunk, chunk after chunk (alternating which runs
   first), BLAS limited to one thread as the enrichment engine runs blocks. Prints wall and
   CPU seconds, their ratios and the trees found; with ``--same`` (a change that must not
   change the segmentation) checks that both give the same trees, point labels and tree
   ids (stem fits to 1e-9 m).
"""

from __future__ import annotations

import argparse
import io
import pickle
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

#: Run in the baseline's subprocess: segment the chunk given, pickle labels, ids, table, time.
_RUN_ONE = """
import pickle, sys, time
from threadpoolctl import threadpool_limits
from standgrid.enrichment.trees import segment_trees
xyz, heights, options = pickle.loads(open(sys.argv[1], "rb").read())
with threadpool_limits(1):
    segment_trees(xyz[:20000], heights[:20000], **options)  # imports, not timed
    c0, t0 = time.process_time(), time.perf_counter()
    seg = segment_trees(xyz, heights, **options)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
out = (seg.labels, seg.point_tree_ids(), seg.table.drop(columns=["crown"]), wall, cpu)
open(sys.argv[2], "wb").write(pickle.dumps(out))
"""


def capture(catalog: Path, workdir: Path) -> list[Path]:
    """The saved inputs of every ``segment_trees`` call of an enrichment of ``catalog``."""
    import standgrid.enrichment.trees as trees
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.pipeline.enrich import enrich_catalog

    saved = sorted(workdir.glob("chunk_*.pkl"))
    if saved:
        return saved
    workdir.mkdir(parents=True, exist_ok=True)
    original = trees.segment_trees

    def keep(points: Any, heights: Any, **options: Any) -> Any:
        path = workdir / f"chunk_{len(saved):03d}.pkl"
        path.write_bytes(pickle.dumps((np.asarray(points), np.asarray(heights), options)))
        saved.append(path)
        return original(points, heights, **options)

    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "catalog"
        shutil.copytree(catalog, copy)
        trees.segment_trees = keep  # type: ignore[assignment]
        try:
            enrich_catalog(copy, EnrichOptions())
        finally:
            trees.segment_trees = original  # type: ignore[assignment]
    return saved


def baseline_tree(rev: str) -> Path:
    """A folder holding the ``standgrid`` package as it was at ``rev``."""
    archive = subprocess.run(
        ["git", "-C", str(REPO), "archive", rev, "standgrid"], check=True, capture_output=True
    ).stdout
    folder = Path(tempfile.mkdtemp())
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(folder, filter="data")
    return folder


def run_baseline(folder: Path, chunk: Path) -> tuple[Any, ...]:
    out = Path(tempfile.mkstemp(suffix=".pkl")[1])
    env = {"PYTHONPATH": str(folder), "PATH": "/usr/bin:/bin"}
    subprocess.run(
        [sys.executable, "-c", _RUN_ONE, str(chunk), str(out)], check=True, env=env, cwd=folder
    )
    result = pickle.loads(out.read_bytes())
    out.unlink()
    return tuple(result)


def compare(old: tuple[Any, ...], new: Any) -> dict[str, float]:
    """Asserts the same segmentation; returns the largest difference per float column."""
    labels, ids, a, _, _ = old
    assert np.array_equal(labels, new.labels)
    assert np.array_equal(ids, new.point_tree_ids())
    b = new.table.drop(columns=["crown"])
    assert list(a.columns) == list(b.columns) and len(a) == len(b)
    worst = {}
    for column in a.columns:
        x, y = a[column], b[column]
        if x.dtype.kind == "f":
            u, v = x.to_numpy(), y.to_numpy()
            assert np.array_equal(np.isnan(u), np.isnan(v)), column
            diff = np.abs(u - v)[~np.isnan(u)]
            worst[column] = float(diff.max()) if len(diff) else 0.0
            assert worst[column] <= 1e-9, (column, worst[column])
        else:
            assert x.equals(y), column
    return worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("catalog", type=Path)
    parser.add_argument("--baseline", required=True, help="git revision to compare against")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "trees")
    parser.add_argument("--same", action="store_true", help="check the same segmentation")
    args = parser.parse_args()

    from threadpoolctl import threadpool_limits

    import standgrid.enrichment.trees as new

    chunks = capture(args.catalog, args.workdir)
    folder = baseline_tree(args.baseline)
    wall = {"old": 0.0, "new": 0.0}
    cpu = {"old": 0.0, "new": 0.0}
    trees = {"old": 0, "new": 0}
    worst: dict[str, float] = {}
    n_points = 0
    for k, path in enumerate(chunks):
        xyz, heights, options = pickle.loads(path.read_bytes())
        for name in ("old", "new") if k % 2 == 0 else ("new", "old"):
            if name == "old":
                old = run_baseline(folder, path)
                wall["old"] += old[3]
                cpu["old"] += old[4]
                trees["old"] += len(old[2])
                continue
            with threadpool_limits(1):
                c0, t0 = time.process_time(), time.perf_counter()
                result = new.segment_trees(xyz, heights, **options)
                wall["new"] += time.perf_counter() - t0
                cpu["new"] += time.process_time() - c0
            trees["new"] += len(result.table)
        if args.same:
            for column, value in compare(old, result).items():
                worst[column] = max(worst.get(column, 0.0), value)
        n_points += len(xyz)
    print(
        f"{len(chunks)} chunks, {n_points:,} points; trees: baseline {trees['old']}, "
        f"this tree {trees['new']}"
    )
    if args.same:
        print(
            "same segmentation; largest difference per float column:",
            {k: f"{v:.1e}" for k, v in worst.items()},
        )
    for label, seconds in (("wall", wall), ("CPU", cpu)):
        print(
            f"{label}: baseline {seconds['old']:.2f} s, this tree {seconds['new']:.2f} s, "
            f"ratio {seconds['new'] / seconds['old']:.3f} ({seconds['old'] / seconds['new']:.2f}x)"
        )
    shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
