"""Ground and terrain of a block of points (what enrichment builds everything else on).

1. CSF (:func:`standgrid.enrich.ground.classify_ground`) runs over the lowest return of
   each quarter cloth cell (the returns the cloth comes to rest on: a 30-40x smaller cloud
   for dense scans), once over the whole block and once square by square
   (:data:`GROUND_SQUARE_M` on a fixed lattice, each with :data:`GROUND_HALO_M` around it);
   a return either calls ground is ground (see :func:`_classify`);
2. the terrain model is the TIN of that ground, thinned to one point per half pixel, at the
   window's pixel centres (nearest ground point outside their hull);
3. every return within :data:`CLASS_THRESHOLD_M` of the terrain (CSF's own class threshold)
   is ground; heights above ground are bilinear in the terrain model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from standgrid.enrich.ground import classify_ground
from standgrid.enrich.rasters import RasterGrid, dtm_from_ground, height_above_ground
from standgrid.errors import EnrichError, StandgridError


@dataclass(frozen=True)
class Terrain:
    """``ground`` (mask per point), ``dtm`` (on the window; NaN without ground) and
    ``heights`` (float32 per point; NaN without ground)."""

    ground: NDArray[np.bool_]
    dtm: NDArray[np.float32]
    heights: NDArray[np.float32]


def classify_terrain(
    xyz: NDArray[np.float64],
    window: RasterGrid,
    *,
    lattice: tuple[float, float] = (0.0, 0.0),
    cloth_resolution: float = 0.5,
    rigidness: int = 1,
    source: str | None = None,
) -> Terrain:
    """Ground, terrain model and heights of ``xyz`` (all inside ``window``); the CSF squares
    sit on ``lattice`` (the same for every block, so blocks agree)."""
    lowest = _lowest(xyz, cloth_resolution / 2)
    cloth = lowest[_classify(xyz[lowest], lattice, cloth_resolution, rigidness, source)]
    if len(cloth) == 0:
        return Terrain(
            np.zeros(len(xyz), dtype=bool),
            np.full(window.shape, np.nan, dtype=np.float32),
            np.full(len(xyz), np.nan, dtype=np.float32),
        )
    dtm = _dtm(xyz[cloth], window)
    heights = height_above_ground(xyz, dtm, window)
    return Terrain(np.abs(heights) <= CLASS_THRESHOLD_M, dtm, heights)


#: Ground points this far outside a DTM window still shape its triangulation (m).
DTM_MARGIN_M = 3.0
#: A return this close to the terrain (m) is ground (CSF's class threshold).
CLASS_THRESHOLD_M = 0.5
#: Ground is classified in squares of this side (m), on a fixed lattice ...
GROUND_SQUARE_M = 40.0
#: ... each seen with this much around it (m).
GROUND_HALO_M = 10.0
def _classify(
    xyz: NDArray[np.float64],
    lattice: tuple[float, float],
    cloth_resolution: float,
    rigidness: int,
    source: str | None,
) -> NDArray[np.bool_]:
    """Ground mask of the block: ground for CSF over the whole block, or for CSF over the
    square (:data:`GROUND_SQUARE_M` on ``lattice``, seen with :data:`GROUND_HALO_M` around
    it) holding the point. CSF misses ground near the data's edge on one scale or the other
    (measured: over a whole 80 m block with relief it misses ground along a survey edge that
    40 m squares find; over a 30 m strip of a 25 deg slope it misses the upslope edge that
    the whole 60 m slope finds), and it calls almost nothing ground that is not (< 0.01 %
    of the vegetation over 1 m), so the union keeps the best of both."""
    ground = np.zeros(len(xyz), dtype=bool)
    if len(xyz) < 3:
        return ground
    x, y = xyz[:, 0], xyz[:, 1]
    kx = np.floor((x - lattice[0]) / GROUND_SQUARE_M).astype(np.int64)
    ky = np.floor((y - lattice[1]) / GROUND_SQUARE_M).astype(np.int64)
    h = GROUND_HALO_M
    for ix, iy in sorted(set(zip(kx.tolist(), ky.tolist(), strict=True))):
        x0 = lattice[0] + ix * GROUND_SQUARE_M
        y0 = lattice[1] + iy * GROUND_SQUARE_M
        x1, y1 = x0 + GROUND_SQUARE_M, y0 + GROUND_SQUARE_M
        near = np.flatnonzero((x >= x0 - h) & (x < x1 + h) & (y >= y0 - h) & (y < y1 + h))
        own = (kx[near] == ix) & (ky[near] == iy)
        ground[near[own]] = _csf(xyz[near], cloth_resolution, rigidness, source)[own]
    return ground | _csf(xyz, cloth_resolution, rigidness, source)


def _lowest(xyz: NDArray[np.float64], size: float) -> NDArray[np.int64]:
    """Rows of the lowest point of each ``size`` square (ties: every tied point), sorted."""
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.int64)
    cell = np.floor((xyz[:, :2] - xyz[:, :2].min(axis=0)) / size).astype(np.int64)
    key = cell[:, 0] * (int(cell[:, 1].max()) + 1) + cell[:, 1]
    low = np.full(int(key.max()) + 1, np.inf)
    np.minimum.at(low, key, xyz[:, 2])
    return np.flatnonzero(xyz[:, 2] <= low[key])


def _csf(
    xyz: NDArray[np.float64], cloth_resolution: float, rigidness: int, source: str | None
) -> NDArray[np.bool_]:
    if len(xyz) < 3:
        return np.zeros(len(xyz), dtype=bool)
    try:
        return classify_ground(xyz, cloth_resolution=cloth_resolution, rigidness=rigidness)
    except StandgridError:
        raise
    except Exception as exc:  # CSF is a C++ extension: name the chunk it failed on
        raise EnrichError(f"ground classification failed: {exc}", path=source) from exc


def _dtm(ground: NDArray[np.float64], window: RasterGrid) -> NDArray[np.float32]:
    """The window's DTM from the ground points near it, thinned to half a pixel."""
    xmin, ymin, xmax, ymax = window.bounds
    m = DTM_MARGIN_M
    x, y = ground[:, 0], ground[:, 1]
    near = (x >= xmin - m) & (x <= xmax + m) & (y >= ymin - m) & (y <= ymax + m)
    chosen = ground[near] if near.sum() >= 3 else ground
    return dtm_from_ground(thin(chosen, window.pixel_size / 2), window)


def thin(points: NDArray[np.float64], spacing: float) -> NDArray[np.float64]:
    """At most one point per ``spacing`` square (the first in file order, so unbiased in z):
    a terrain model at pixel size p needs no more than ~4 ground points per p^2."""
    if len(points) < 1000:
        return points
    bins = np.floor((points[:, :2] - points[:, :2].min(axis=0)) / spacing).astype(np.int64)
    keys = bins[:, 0] * (int(bins[:, 1].max()) + 1) + bins[:, 1]
    _, first = np.unique(keys, return_index=True)
    return points[np.sort(first)]


