"""Enrichment's terrain and raster passes against a baseline revision's, same run, same chunks.

Usage::

    python benchmarks/bench_terrain_passes.py CATALOG [--baseline 2d5c793] [--chunks N]

For every chunk of CATALOG (a 20 m grid; chunks planned as ``enrich_catalog`` plans them
with the default 10 m halo, read as ``run_block`` reads them), back to back in this
process, in alternating order, after one untimed round on the first chunk:

- terrain pass: ``classify_terrain`` (ground, DTM, heights);
- raster pass: ground hits, block CHM, density and the observed flag of the owned points,
  as ``enrich_block`` computes them (the baseline from the points' coordinates, the working
  tree from the pixels the terrain pass found);
- tree CHM: ``chm`` with the pit-free subcircle, as ``segment_trees`` calls it.

Every output is asserted bit-identical (NaN where NaN, signs of zeros included). The
baseline's ``standgrid/enrichment/{terrain,rasters}.py`` are taken from git (``git show``).
Prints CPU seconds of both and the share saved.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def baseline_modules(revision: str, folder: Path) -> tuple[Any, Any]:
    """The baseline's rasters and terrain modules, importable beside the working tree's."""

    def load(name: str, source: str) -> Any:
        path = folder / f"{name}.py"
        path.write_text(source)
        spec = importlib.util.spec_from_file_location(name, path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        return module

    def show(path: str) -> str:
        return subprocess.run(
            ["git", "-C", str(REPO), "show", f"{revision}:{path}"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout

    rasters = load("baseline_rasters", show("standgrid/enrichment/rasters.py"))
    terrain_source = show("standgrid/enrichment/terrain.py").replace(
        "from standgrid.enrichment.rasters import", "from baseline_rasters import"
    )
    return rasters, load("baseline_terrain", terrain_source)


def identical(a: Any, b: Any) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.dtype.kind != "f":
        return bool(np.array_equal(a, b))
    return bool(np.array_equal(a, b, equal_nan=True) and (np.signbit(a) == np.signbit(b)).all())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("catalog", type=Path)
    parser.add_argument("--baseline", default="2d5c793", help="git revision to compare with")
    parser.add_argument("--chunks", type=int, default=0, help="only the first N chunks")
    args = parser.parse_args()

    import pyogrio
    import shapely

    import standgrid.enrichment.coverage as coverage
    import standgrid.enrichment.rasters as rasters
    import standgrid.enrichment.terrain as terrain
    from standgrid.engine import Execution
    from standgrid.enrichment.block import _window
    from standgrid.enrichment.chunks import (
        BYTES_PER_POINT,
        cells_of,
        chunk_side,
        plan_chunks,
        read_chunk,
    )
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.enrichment.trees import CHM_SUBCIRCLE_M

    old_rasters, old_terrain = baseline_modules(args.baseline, Path(tempfile.mkdtemp()))
    cells = cells_of(pyogrio.read_dataframe(args.catalog / "index.gpkg", layer="cells"))
    state = json.loads((args.catalog / "catalog.json").read_text())
    origin = tuple(state["grid"]["origin"])
    options = EnrichOptions()
    budget = Execution().memory_budget.bytes * 7 // 8 // BYTES_PER_POINT
    side = chunk_side(cells, 20.0, options.halo, budget)
    chunks = plan_chunks(cells, side=side, origin=origin, buffer=options.halo)
    chunks = chunks[: args.chunks] if args.chunks else chunks
    bounds = shapely.bounds(shapely.union_all([c.polygon for c in cells]))
    grid = rasters.RasterGrid.covering(
        tuple(bounds), origin=origin, cell_size=20.0, pixel_size=options.pixel_size, closed=True
    )
    lattice = (grid.x0, grid.y0)
    cpu: dict[str, list[float]] = {}

    def both(name: str, old: Callable[[], Any], new: Callable[[], Any], k: int) -> Any:
        times = cpu.setdefault(name, [0.0, 0.0])
        results: list[Any] = [None, None]
        for which in (0, 1) if k % 2 else (1, 0):  # alternate which runs first
            start = time.process_time()
            results[which] = (old, new)[which]()
            times[which] += time.process_time() - start
        return results

    def compare(k: int, block: Any, window: Any) -> None:
        """Both versions' passes on one chunk: outputs identical, CPU time added up."""
        xyz = block.xyz
        old_window = baseline_grid(window)
        was, now = both(
            "terrain",
            lambda: old_terrain.classify_terrain(xyz, old_window, lattice=lattice),
            lambda: terrain.classify_terrain(xyz, window, lattice=lattice),
            k,
        )
        for field in ("ground", "dtm", "heights"):
            assert identical(getattr(was, field), getattr(now, field)), (k, field)
        hag, ground, pixels = now.heights, now.ground, now.pixels
        hits = coverage.ground_hits(window, xyz[ground, :2])
        observed = coverage.coverage_from_hits(hits, window, np.ones(window.shape, dtype=bool))

        def old_pass() -> list[Any]:
            finite = np.isfinite(hag)
            return [
                coverage.ground_hits(window, xyz[ground, :2]),
                old_rasters.chm(xyz[finite], hag[finite], old_window),
                old_rasters.density(xyz, old_window),
                *(observed.observed_at(xyz[rows, 0], xyz[rows, 1]) for rows in block.cell_rows),
            ]

        def new_pass() -> list[Any]:
            return [
                rasters.pixel_counts(pixels[ground], window),
                rasters.chm_from_pixels(pixels, hag, window),
                rasters.density_from_pixels(pixels, window),
                *(observed.observed_in(pixels[rows]) for rows in block.cell_rows),
            ]

        was, now = both("rasters", old_pass, new_pass, k)
        assert all(identical(a, b) for a, b in zip(was, now, strict=True)), k
        canopy = np.isfinite(hag) & (hag >= options.tree_min_height)
        if canopy.any():  # the tree CHM as segment_trees asks for it
            cx, cz = xyz[canopy], hag[canopy].astype(np.float64)
            lo, hi = cx[:, :2].min(axis=0), cx[:, :2].max(axis=0)
            size = options.tree_pixel_size
            tree_grid = rasters.RasterGrid.covering(
                (lo[0], lo[1], hi[0], hi[1]), origin=(0.0, 0.0), cell_size=size, pixel_size=size
            )
            old_grid = baseline_grid(tree_grid)
            was, now = both(
                "tree CHM",
                lambda: old_rasters.chm(cx, cz, old_grid, subcircle=CHM_SUBCIRCLE_M),
                lambda: rasters.chm(cx, cz, tree_grid, subcircle=CHM_SUBCIRCLE_M),
                k,
            )
            assert identical(was, now), k

    def baseline_grid(grid: Any) -> Any:
        return old_rasters.RasterGrid(grid.x0, grid.y0, grid.pixel_size, grid.ncols, grid.nrows)

    n_points = 0
    for k, chunk in enumerate(chunks):
        block = read_chunk(args.catalog, chunk, origin)
        window = _window(grid, chunk.buffered_bounds)
        if k == 0:  # once before the clock: imports, thread pools, first calls
            compare(k, block, window)
            cpu.clear()
        compare(k, block, window)
        n_points += len(block.xyz)
    print(f"{len(chunks)} chunks, {n_points} block points: every output identical")
    for name, (old, new) in cpu.items():
        print(
            f"{name:9s} baseline {old:6.2f} s, now {new:6.2f} s CPU: "
            f"{(old - new) / old * 100:4.1f} % less (x{old / new:.2f})"
        )


if __name__ == "__main__":
    main()
