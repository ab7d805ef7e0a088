"""The 1 mm storage lattice of tiles: coordinates are snapped to it before cells are assigned."""

from __future__ import annotations

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
