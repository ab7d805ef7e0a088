"""RasterGrid: a CRS-carrying value with windows (for a bbox, a window's grid, the affine)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from standgrid.crs import CRS
from standgrid.geotiff import read_grid, read_window, write_cog
from standgrid.rastergrid import RasterGrid

GRID = RasterGrid(1000.0, 2000.0, 0.5, ncols=40, nrows=20, crs="EPSG:32630")


def test_grid_is_an_immutable_value_carrying_its_crs() -> None:
    assert GRID.crs == CRS.of(32630)
    assert RasterGrid(1000.0, 2000.0, 0.5, 40, 20, CRS.of("EPSG:32630")) == GRID
    assert dataclasses.replace(GRID, crs=None) != GRID
    assert hash(GRID) == hash(RasterGrid(1000.0, 2000.0, 0.5, 40, 20, "EPSG:32630"))
    with pytest.raises(dataclasses.FrozenInstanceError):
        GRID.x0 = 0.0  # type: ignore[misc]
    assert tuple(GRID.transform)[:6] == (0.5, 0.0, 1000.0, 0.0, -0.5, 2010.0)


def test_window_for_a_bbox_and_its_grid() -> None:
    window = GRID.window((1002.2, 2001.0, 1004.0, 2003.1))  # cols 4..8, rows from south 2..7
    assert (window.col_off, window.row_off, window.width, window.height) == (4, 13, 4, 5)
    sub = GRID.window_grid(window)
    assert sub == RasterGrid(1002.0, 2001.0, 0.5, 4, 5, GRID.crs)
    assert sub.bounds[0] <= 1002.2 and sub.bounds[2] >= 1004.0 and sub.bounds[3] >= 2003.1
    # the window's pixels are the grid's: same centres
    xs, ys = GRID.centers()
    sx, sy = sub.centers()
    rows, cols = window.toslices()
    assert np.array_equal(xs[rows, cols], sx) and np.array_equal(ys[rows, cols], sy)


def test_window_clips_to_the_grid_unless_asked_for_the_lattice() -> None:
    beyond = (990.0, 1995.0, 1001.0, 2001.0)
    clipped = GRID.window(beyond)
    assert (clipped.col_off, clipped.width, clipped.row_off + clipped.height) == (0, 2, 20)
    lattice = GRID.window(beyond, clip=False)
    assert (lattice.col_off, lattice.width) == (-20, 22)
    assert GRID.window_grid(lattice).bounds == (990.0, 1995.0, 1001.0, 2001.0)


def test_written_grid_reads_back_with_its_crs_and_windows(tmp_path) -> None:
    data = np.arange(GRID.nrows * GRID.ncols, dtype=np.float32).reshape(GRID.shape)
    path = tmp_path / "r.tif"
    write_cog(path, data, GRID)
    assert read_grid(path) == GRID
    window = GRID.window((1001.0, 2004.0, 1003.0, 2006.0))
    assert np.array_equal(read_window(path, window), data[window.toslices()])
