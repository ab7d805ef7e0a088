"""The 1 mm storage lattice of tiles (coordinates are snapped to it before cells are
assigned), and squares on a lattice (bins every block of an epoch draws the same way)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

#: Coordinate resolution of every tile (1 mm).
SCALE = 0.001
#: Rows snapped per block by :func:`snap_to_storage`.
_SNAP_BLOCK_ROWS = 8192


def snap_to_storage(
    xyz: NDArray[np.float64],
    origin: tuple[float, float] = (0.0, 0.0),
    *,
    out: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Snap coordinates to the 1 mm lattice tiles store, counted from a grid ``origin``.

    ``o + round((v - o) * 1000) / 1000`` is correctly rounded, so a value on a cell edge
    ``o + k * size`` comes out as exactly the float the grid computes for that edge, and a
    coordinate read back from a tile (which may differ by an ulp) snaps to the same value.
    Assign cells on snapped coordinates and every point stays in its cell when re-read.
    ``out`` (may be ``xyz`` itself: snapped in place) receives the result.
    """
    pts = np.asarray(xyz, dtype=np.float64)
    if out is None:
        out = np.empty_like(pts)
    per_mm = 1.0 / SCALE
    origins = (float(origin[0]), float(origin[1]), 0.0)
    # block by block of rows, each axis worked on in a contiguous scratch column (in cache)
    rows = max(1, min(len(pts), _SNAP_BLOCK_ROWS))
    scratch = np.empty(rows)
    for start in range(0, len(pts), rows):
        part = pts[start : start + rows]
        column = scratch[: len(part)]
        for axis, o in enumerate(origins):
            np.subtract(part[:, axis], o, out=column)
            column *= per_mm
            np.round(column, out=column)
            column /= per_mm
            column += o
            out[start : start + len(part), axis] = column
    return out


def lattice_index(values: NDArray[np.float64], origin: float, size: float) -> NDArray[np.int64]:
    """Per value, its ``size`` interval on the lattice of ``origin``: floor((v - o) / size)."""
    index = values - origin
    index /= size
    return np.floor(index, out=index).astype(np.int64)


def square_keys(
    xy: NDArray[np.float64], size: float, lattice: tuple[float, float]
) -> NDArray[np.int64]:
    """Per point, its ``size`` square on ``lattice``, as one integer key (keys order the
    squares by column, then row; their range follows the points' extent)."""
    xy = np.asarray(xy, dtype=np.float64)
    x, y = xy[:, 0], xy[:, 1]
    # a square's index grows with the coordinate: the extreme points give the key's range
    # (only the key's: the squares stay the lattice's)
    col0 = math.floor((float(x.min()) - lattice[0]) / size)
    row0 = math.floor((float(y.min()) - lattice[1]) / size)
    rows = math.floor((float(y.max()) - lattice[1]) / size) - row0 + 1
    key = np.empty(len(xy), dtype=np.int64)
    for start in range(0, len(xy), _BLOCK):  # blocks that stay in the CPU's cache
        part = slice(start, start + _BLOCK)
        col = lattice_index(x[part], lattice[0], size)
        col -= col0
        col *= rows
        col += lattice_index(y[part], lattice[1], size)
        np.subtract(col, row0, out=key[part])
    return key


def lowest_in_squares(
    xyz: NDArray[np.float64], size: float, lattice: tuple[float, float]
) -> NDArray[np.int64]:
    """Rows of the lowest point of each ``size`` square of ``lattice`` (ties: every tied
    point), sorted."""
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.int64)
    key = square_keys(xyz[:, :2], size, lattice)
    low = np.full(int(key.max()) + 1, np.inf)
    np.minimum.at(low, key, xyz[:, 2])
    return np.flatnonzero(xyz[:, 2] <= low[key])


#: Points per block of element-wise arithmetic.
_BLOCK = 1 << 16
