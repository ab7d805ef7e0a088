"""The 1 mm storage lattice of tiles: coordinates are snapped to it before cells are assigned."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

#: Coordinate resolution of every tile (1 mm).
SCALE = 0.001


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
    for axis, o in enumerate((float(origin[0]), float(origin[1]), 0.0)):
        np.subtract(pts[:, axis], o, out=out[:, axis])
        out[:, axis] *= per_mm
        np.round(out[:, axis], out=out[:, axis])
        out[:, axis] /= per_mm
        out[:, axis] += o
    return out
