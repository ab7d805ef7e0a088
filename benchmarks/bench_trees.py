"""``segment_trees`` of this tree against a baseline revision, on the chunks of a real epoch.

Usage::

    python benchmarks/bench_trees.py CATALOG --baseline REV [--workdir DIR]

1. Enriches a copy of the tiled ``CATALOG`` (``enrich_catalog``, one process) and keeps the
   inputs of every chunk's ``segment_trees`` call (points, heights above ground, keywords)
   in ``--workdir`` (reused when present).
2. Times the baseline's ``segment_trees`` (``git show REV:standgrid/enrich/trees.py``) and
   this tree's back to back on each chunk (alternating which goes first), BLAS limited to one
   thread as the enrichment engine runs blocks, and checks that they give the same trees,
   point labels and tree ids (stem fits to 1e-9 m). Prints wall and CPU seconds and ratios.
"""

from __future__ import annotations

import argparse
import importlib.util
import pickle
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def capture(catalog: Path, workdir: Path) -> list[Path]:
    """The saved inputs of every ``segment_trees`` call of an enrichment of ``catalog``."""
    import standgrid.enrich.trees as trees
    from standgrid.pipeline.enrich import EnrichOptions, enrich_catalog

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


def baseline_module(rev: str) -> ModuleType:
    source = subprocess.run(
        ["git", "-C", str(REPO), "show", f"{rev}:standgrid/enrich/trees.py"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    path = Path(tempfile.mkdtemp()) / "baseline_trees.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("baseline_trees", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["baseline_trees"] = module
    spec.loader.exec_module(module)
    return module


def compare(old: Any, new: Any) -> dict[str, float]:
    """Asserts the same segmentation; returns the largest difference per float column."""
    assert np.array_equal(old.labels, new.labels)
    assert np.array_equal(old.point_tree_ids(), new.point_tree_ids())
    a, b = old.table, new.table
    assert list(a.columns) == list(b.columns) and len(a) == len(b)
    worst = {}
    for column in a.columns:
        x, y = a[column], b[column]
        if column == "crown":
            assert all(p is q or p.equals_exact(q, 0.0) for p, q in zip(x, y, strict=True))
        elif x.dtype.kind == "f":
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
    args = parser.parse_args()

    from threadpoolctl import threadpool_limits

    import standgrid.enrich.trees as new

    chunks = capture(args.catalog, args.workdir)
    old = baseline_module(args.baseline)
    wall = {"old": 0.0, "new": 0.0}
    cpu = {"old": 0.0, "new": 0.0}
    worst: dict[str, float] = {}
    n_points = n_trees = 0
    with threadpool_limits(1):
        for k, path in enumerate(chunks):
            xyz, heights, options = pickle.loads(path.read_bytes())
            results = {}
            for name in ("old", "new") if k % 2 == 0 else ("new", "old"):
                module = old if name == "old" else new
                c0, t0 = time.process_time(), time.perf_counter()
                results[name] = module.segment_trees(xyz, heights, **options)
                wall[name] += time.perf_counter() - t0
                cpu[name] += time.process_time() - c0
            for column, value in compare(results["old"], results["new"]).items():
                worst[column] = max(worst.get(column, 0.0), value)
            n_points += len(xyz)
            n_trees += len(results["new"].table)
    print(f"{len(chunks)} chunks, {n_points:,} points, {n_trees} trees: same segmentation")
    print("largest difference per float column:", {k: f"{v:.1e}" for k, v in worst.items()})
    for label, seconds in (("wall", wall), ("CPU", cpu)):
        print(
            f"{label}: baseline {seconds['old']:.2f} s, this tree {seconds['new']:.2f} s, "
            f"ratio {seconds['new'] / seconds['old']:.3f} ({seconds['old'] / seconds['new']:.2f}x)"
        )


if __name__ == "__main__":
    main()
