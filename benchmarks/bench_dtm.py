"""The DTM pass (``dtm_from_ground``) against the algorithm it replaced, same ground, same run.

Usage::

    python benchmarks/bench_dtm.py [--repeat N]

Before issue 22, ``dtm_from_ground`` let scipy compute every triangle's barycentric
transform (a few 2x2 LAPACK calls per triangle); now they are computed in closed form for
all triangles at once, scipy still triangulating and locating the pixels. The old algorithm
is copied below. Ground: a terrain surface with 1 cm LAS quantisation and 5 cm noise,
thinned as the terrain pass thins it (``thin`` at half a pixel, so exact ties on the
lattice), on a 200 x 200 m chunk at 0.5 m pixels (50k to 500k ground points) and a 1 ha
chunk at 0.5 m, with ``max_edge`` = 10 m as ``classify_terrain`` asks. One BLAS and one
OpenMP thread (as the engine runs tasks). Prints CPU seconds (``time.process_time``) of
both, their ratio and the largest difference of the DTMs (float32, m).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from standgrid.enrichment.rasters import dtm_from_ground
from standgrid.enrichment.terrain import DTM_MARGIN_M, thin
from standgrid.rastergrid import RasterGrid


def old_dtm_from_ground(
    xyz: np.ndarray, grid: RasterGrid, max_edge: float | None = None
) -> np.ndarray:
    """``dtm_from_ground`` as it was before issue 22 (the reference)."""
    from scipy.interpolate import LinearNDInterpolator
    from scipy.spatial import Delaunay, QhullError, cKDTree

    local = xyz[:, :2] - (grid.x0, grid.y0)
    cx, cy = grid.centers()
    query = np.column_stack([cx.ravel() - grid.x0, cy.ravel() - grid.y0])
    values = np.full(len(query), np.nan)
    if len(xyz) >= 3:
        with contextlib.suppress(QhullError):
            tin = Delaunay(local)
            values = LinearNDInterpolator(tin, xyz[:, 2])(query)
            if max_edge is not None:
                corners = tin.points[tin.simplices]
                edges = corners - np.roll(corners, 1, axis=1)
                long = ((edges**2).sum(axis=2) > max_edge**2).any(axis=1)
                simplex = tin.find_simplex(query)
                values[(simplex >= 0) & long[np.maximum(simplex, 0)]] = np.nan
    missing = ~np.isfinite(values)
    if missing.any():
        _, nearest = cKDTree(local).query(query[missing])
        values[missing] = xyz[nearest, 2]
    return values.reshape(grid.shape).astype(np.float32)


def ground(side: float, n: int, pixel: float, seed: int) -> tuple[np.ndarray, RasterGrid]:
    """``n`` raw ground returns over a ``side`` m chunk plus the DTM margin, thinned."""
    rng = np.random.default_rng(seed)
    x0, y0 = 600_000.0, 5_100_000.0
    m = DTM_MARGIN_M
    x = np.round(x0 + rng.uniform(-m, side + m, n), 2)
    y = np.round(y0 + rng.uniform(-m, side + m, n), 2)
    z = np.round(400 + 0.15 * (x - x0) + 3 * np.sin((y - y0) / 25) + rng.normal(0, 0.05, n), 2)
    cells = round(side / pixel)
    grid = RasterGrid(x0=x0, y0=y0, pixel_size=pixel, ncols=cells, nrows=cells)
    return thin(np.column_stack([x, y, z]), pixel / 2, (x0, y0)), grid


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=1, help="runs of each, alternating")
    args = parser.parse_args()
    cases = [
        ("200 m, 0.5 m px", 200.0, 60_000, 0.5),
        ("200 m, 0.5 m px", 200.0, 250_000, 0.5),
        ("200 m, 0.5 m px", 200.0, 1_000_000, 0.5),
        ("1 ha, 0.5 m px", 100.0, 200_000, 0.5),
    ]
    with threadpool_limits(limits=1):
        dtm_from_ground(*ground(20.0, 2000, 0.5, 0))  # imports, first calls
        total = [0.0, 0.0]
        for k, (name, side, n, pixel) in enumerate(cases):
            xyz, grid = ground(side, n, pixel, seed=k)
            runs = (old_dtm_from_ground, dtm_from_ground)
            cpu = [0.0, 0.0]
            out: list[Any] = [None, None]
            for r in range(args.repeat):
                for which in (0, 1) if r % 2 == 0 else (1, 0):  # alternate which runs first
                    start = time.process_time()
                    out[which] = runs[which](xyz, grid, max_edge=DTM_MARGIN_M)
                    cpu[which] += time.process_time() - start
            diff = float(np.abs(out[0].astype(np.float64) - out[1]).max())
            same = int(np.count_nonzero(out[0] != out[1]))
            print(
                f"{name:16s} {len(xyz):7d} ground pts, {grid.ncols * grid.nrows:6d} px: "
                f"old {cpu[0]:7.2f} s, new {cpu[1]:6.2f} s CPU, ratio {cpu[1] / cpu[0]:.3f}; "
                f"max |diff| {diff:.2e} m, {same} pixels differ"
            )
            total[0] += cpu[0]
            total[1] += cpu[1]
        print(
            f"all: old {total[0]:.2f} s, new {total[1]:.2f} s CPU, ratio {total[1] / total[0]:.3f}"
        )


if __name__ == "__main__":
    main()
