"""Ground and terrain of a block of points (what enrichment builds everything else on).

1. CSF (:func:`standgrid.enrichment.ground.classify_ground`) runs over the lowest return of
   each quarter cloth cell (the returns the cloth comes to rest on: a 30-40x smaller cloud
   for dense scans), square by square: :data:`GROUND_SQUARE_M` squares on a fixed lattice
   (the stand grid's), each seen with :data:`GROUND_HALO_M` around it;
2. the terrain model is the TIN of that ground, thinned to the point nearest the centre of
   each half-pixel square, at the window's pixel centres, without triangles longer than
   :data:`DTM_MARGIN_M` (nearest ground point there and outside the hull);
3. every return within :data:`CLASS_THRESHOLD_M` of the terrain (CSF's own class threshold)
   is ground; heights above ground are bilinear in the terrain model.

Every bin and square sits on the fixed lattice and no choice depends on the order of the
points, so a square's ground depends only on the lowest points within
:data:`GROUND_HALO_M` of it, and a pixel's height only on the ground within
:data:`DTM_MARGIN_M` of it. A block that sees the lowest points out to the halo of every
square it touches (:func:`ground_reach`: the chunk's ring) gives every point it owns what
one computation over the whole epoch would, whatever the chunk layout (the memory budget)
is. (Two cases reach further and are left as they are: a pixel more than ~20 m from any
ground takes its nearest ground point, and a thin triangle's circumcircle can reach past
the margin.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from standgrid.enrichment.ground import classify_ground
from standgrid.enrichment.rasters import dtm_from_ground, heights_and_pixels
from standgrid.errors import EnrichError, StandgridError
from standgrid.partition.lattice import lattice_index, lowest_in_squares, square_keys
from standgrid.rastergrid import RasterGrid


@dataclass(frozen=True)
class Terrain:
    """``ground`` (mask per point), ``dtm`` (on the window; NaN without ground),
    ``heights`` (float32 per point; NaN without ground) and ``pixels`` (each point's pixel
    on the window, :meth:`RasterGrid.flat_index`)."""

    ground: NDArray[np.bool_]
    dtm: NDArray[np.float32]
    heights: NDArray[np.float32]
    pixels: NDArray[np.int64]


def classify_terrain(
    xyz: NDArray[np.float64],
    window: RasterGrid,
    *,
    lattice: tuple[float, float] = (0.0, 0.0),
    cloth_resolution: float = 0.5,
    rigidness: int = 1,
    source: str | None = None,
    ring: NDArray[np.float64] | None = None,
) -> Terrain:
    """Ground, terrain model and heights of ``xyz`` (all inside ``window``); bins and CSF
    squares sit on ``lattice`` (the same for every block, so blocks agree). ``ring`` holds
    the lowest point of each bin (:func:`ring_bin`) around the block out to
    :func:`ground_reach` of it: the ground squares the block touches then see all they
    would in the whole epoch."""
    size = ring_bin(cloth_resolution)
    candidates = xyz[lowest_in_squares(xyz, size, lattice)]
    squares = _squares(candidates, lattice)  # the ground squares the block touches
    if ring is not None and len(ring):
        # a bin cut by a tile's or the buffer's edge has a lowest point on each side (a
        # Voronoi cell's edge cuts bins): the lowest of them is the epoch's
        pool = np.concatenate([candidates, ring])
        candidates = pool[lowest_in_squares(pool, size, lattice)]
    ground = _classify(candidates, lattice, cloth_resolution, rigidness, source, squares)
    cloth = candidates[ground]
    # one order for the triangulation, whichever block (and rows) the ground came from
    cloth = cloth[np.lexsort((cloth[:, 2], cloth[:, 1], cloth[:, 0]))]
    if len(cloth) == 0:
        return Terrain(
            np.zeros(len(xyz), dtype=bool),
            np.full(window.shape, np.nan, dtype=np.float32),
            np.full(len(xyz), np.nan, dtype=np.float32),
            window.flat_index(xyz[:, 0], xyz[:, 1]),
        )
    dtm = _dtm(cloth, window, lattice)
    heights, pixels = heights_and_pixels(xyz, dtm, window)
    return Terrain(np.abs(heights) <= CLASS_THRESHOLD_M, dtm, heights, pixels)


#: The terrain model's triangles are at most this long (m; a pixel in a longer one takes the
#: nearest ground point's height, as outside the ground's hull), and ground points this far
#: outside a DTM window still shape it: so a pixel's height depends on the ground within
#: this of it, whichever block computes it.
DTM_MARGIN_M = 10.0
#: A return this close to the terrain (m) is ground (CSF's class threshold).
CLASS_THRESHOLD_M = 0.5
#: Ground is classified in squares of this side (m, a stand cell), on the lattice ...
GROUND_SQUARE_M = 20.0
#: ... each seen with this much around it (m; a chunk brings it: :func:`ground_reach`).
GROUND_HALO_M = 10.0


def ring_bin(cloth_resolution: float) -> float:
    """The side of the bins whose lowest point CSF sees (a quarter cloth cell)."""
    return cloth_resolution / 2


def ground_reach(
    bounds: tuple[float, float, float, float], lattice: tuple[float, float]
) -> tuple[float, float, float, float]:
    """The extent whose lowest points decide the ground of a block over ``bounds``: every
    ground square the block touches, with its halo. A block that sees it classifies its
    squares as the whole epoch would, so its terrain model (whose triangles at the block's
    edge reach into the next squares) is the whole epoch's up to the block's edge."""
    size, halo = GROUND_SQUARE_M, GROUND_HALO_M
    x0 = lattice[0] + math.floor((bounds[0] - lattice[0]) / size) * size
    y0 = lattice[1] + math.floor((bounds[1] - lattice[1]) / size) * size
    x1 = lattice[0] + math.ceil((bounds[2] - lattice[0]) / size) * size
    y1 = lattice[1] + math.ceil((bounds[3] - lattice[1]) / size) * size
    return x0 - halo, y0 - halo, x1 + halo, y1 + halo


def _classify(
    xyz: NDArray[np.float64],
    lattice: tuple[float, float],
    cloth_resolution: float,
    rigidness: int,
    source: str | None,
    squares: list[tuple[int, int]] | None = None,
) -> NDArray[np.bool_]:
    """Ground mask, CSF square by square (:data:`GROUND_SQUARE_M` on ``lattice``, seen with
    :data:`GROUND_HALO_M` around it): the same extent for every square, so the cloth's edge
    effects do not depend on how much of the survey a block holds. Only ``squares`` (default:
    every square holding points) are classified; points elsewhere are only seen."""
    ground = np.zeros(len(xyz), dtype=bool)
    if len(xyz) < 3:
        return ground
    # CSF sees the points sorted by x, y, z: its result may depend on their order, which
    # the block layout would otherwise set. One sort serves every square: a square's
    # points are a run of it in x, filtered by y (a stable sort, so the same order)
    by_xyz = np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))
    x, y = xyz[by_xyz, 0], xyz[by_xyz, 1]
    kx = lattice_index(x, lattice[0], GROUND_SQUARE_M)
    ky = lattice_index(y, lattice[1], GROUND_SQUARE_M)
    h = GROUND_HALO_M
    for ix, iy in _distinct(kx, ky) if squares is None else squares:
        x0 = lattice[0] + ix * GROUND_SQUARE_M
        y0 = lattice[1] + iy * GROUND_SQUARE_M
        x1, y1 = x0 + GROUND_SQUARE_M, y0 + GROUND_SQUARE_M
        start, stop = np.searchsorted(x, [x0 - h, x1 + h])  # x0 - h <= x < x1 + h
        run = slice(start, stop)
        near = start + np.flatnonzero((y[run] >= y0 - h) & (y[run] < y1 + h))
        labels = _csf(xyz[by_xyz[near]], cloth_resolution, rigidness, source)
        mine = (kx[near] == ix) & (ky[near] == iy)
        ground[by_xyz[near[mine]]] = labels[mine]
    return ground


def _squares(xyz: NDArray[np.float64], lattice: tuple[float, float]) -> list[tuple[int, int]]:
    """The ground squares (:data:`GROUND_SQUARE_M` on ``lattice``) holding the points, sorted."""
    if len(xyz) == 0:
        return []
    kx = lattice_index(xyz[:, 0], lattice[0], GROUND_SQUARE_M)
    ky = lattice_index(xyz[:, 1], lattice[1], GROUND_SQUARE_M)
    return _distinct(kx, ky)


def _distinct(kx: NDArray[np.int64], ky: NDArray[np.int64]) -> list[tuple[int, int]]:
    """The distinct (kx, ky) pairs, sorted."""
    kx0, ky0 = int(kx.min()), int(ky.min())
    rows = int(ky.max()) - ky0 + 1
    key = (kx - kx0) * rows + (ky - ky0)  # grows with (kx, ky) in lexicographic order
    ix, iy = np.divmod(np.unique(key), rows)
    return list(zip((ix + kx0).tolist(), (iy + ky0).tolist(), strict=True))


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


def _dtm(
    ground: NDArray[np.float64], window: RasterGrid, lattice: tuple[float, float]
) -> NDArray[np.float32]:
    """The window's DTM from the ground points near it, thinned to half a pixel."""
    xmin, ymin, xmax, ymax = window.bounds
    m = DTM_MARGIN_M
    x, y = ground[:, 0], ground[:, 1]
    near = (x >= xmin - m) & (x <= xmax + m) & (y >= ymin - m) & (y <= ymax + m)
    chosen = ground[near] if near.sum() >= 3 else ground
    return dtm_from_ground(thin(chosen, window.pixel_size / 2, lattice), window, max_edge=m)


def thin(
    points: NDArray[np.float64], spacing: float, lattice: tuple[float, float] = (0.0, 0.0)
) -> NDArray[np.float64]:
    """The point nearest the centre of each ``spacing`` square of ``lattice`` (ties by x, y,
    z; unbiased in z, independent of the points' order): a terrain model at pixel size p
    needs no more than ~4 ground points per p^2."""
    if len(points) < 1000:
        return points
    key = square_keys(points[:, :2], spacing, lattice)
    dist = np.zeros(len(points))
    for axis in range(2):  # squared distance to the square's centre, in squares
        units = (points[:, axis] - lattice[axis]) / spacing
        offset = units - (np.floor(units) + 0.5)
        offset *= offset
        dist += offset
    nearest = np.full(int(key.max()) + 1, np.inf)
    np.minimum.at(nearest, key, dist)
    # only the points nearest their square's centre can be first, all at the same
    # distance: a square with one such point keeps it, the others keep their first by x, y, z
    tied = np.flatnonzero(dist <= nearest[key])
    by_square = tied[np.argsort(key[tied], kind="stable")]
    square = key[by_square]
    same = square[1:] == square[:-1]
    shared = np.zeros(len(by_square), dtype=bool)
    shared[1:] |= same
    shared[:-1] |= same
    chosen = by_square[~shared]
    if shared.any():
        rivals = by_square[shared]
        by = points[rivals]
        order = rivals[np.lexsort((by[:, 2], by[:, 1], by[:, 0], key[rivals]))]
        first = np.r_[True, key[order][1:] != key[order][:-1]]
        chosen = np.concatenate([chosen, order[first]])
    return points[np.sort(chosen)]
