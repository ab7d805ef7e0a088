"""Terrain and canopy rasters pixel-aligned to the stand grid (DTM, heights, CHM, density).

Their :class:`~standgrid.rastergrid.RasterGrid` is a pixel lattice whose pixel size divides
the stand cell size and whose corner lies on the stand grid origin plus an integer number of
pixels, so rasters of every epoch (and every stand cell) overlay pixel for pixel; they are
written by :func:`standgrid.geotiff.write_cog`.
"""

from __future__ import annotations

import contextlib
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid.enrichment.ground import PointsLike, as_xyz, one_thread
from standgrid.errors import EnrichError
from standgrid.rastergrid import BLOCK, RasterGrid, blocks

#: An empty CHM pixel is filled when at least this many of its 8 neighbours hold a height.
FILL_MIN_NEIGHBOURS = 6


def dtm_from_ground(
    ground: PointsLike, grid: RasterGrid, *, max_edge: float | None = None
) -> NDArray[np.float32]:
    """Digital terrain model: Delaunay (TIN) linear interpolation of the ground points at pixel
    centres, nearest ground point outside their convex hull and, given ``max_edge`` (m, as
    lidR's ``tin(max_edge=)``), inside triangles with a longer edge: a pixel's value then
    depends only on the ground within ``max_edge`` of it (or, past that, on the nearest),
    not on how far the survey's hull reaches.

    scipy triangulates (qhull) and locates the pixels (its walk: ties on shared edges and on
    the hull resolved as ever), but the triangles' barycentric transforms, which scipy
    computes with a few LAPACK calls per triangle (most of the cost: 2/3 or more), are
    computed here in closed form for all triangles at once (:func:`_barycentric_transforms`):
    equal to rounding, the values match scipy's own within ~1e-12 m (bit for bit as float32
    in practice) and every pixel takes the same triangle or nearest ground point.
    """
    from scipy.interpolate import LinearNDInterpolator
    from scipy.spatial import Delaunay, QhullError, cKDTree

    xyz = as_xyz(ground)
    if len(xyz) == 0:
        raise EnrichError("no ground points: cannot build a terrain model")
    local = xyz[:, :2] - (grid.x0, grid.y0)  # local origin: precise triangulation
    cx, cy = grid.centers()
    query = np.column_stack([cx.ravel() - grid.x0, cy.ravel() - grid.y0])
    values = np.full(len(query), np.nan)
    if len(xyz) >= 3:
        with contextlib.suppress(QhullError):  # collinear: nearest below
            tin = Delaunay(local)
            _set_barycentric_transforms(tin)
            values = LinearNDInterpolator(tin, xyz[:, 2])(query)
            if max_edge is not None:
                values[_in_long_triangles(tin, query, max_edge)] = np.nan
    missing = ~np.isfinite(values)
    if missing.any():
        _, nearest = cKDTree(local).query(query[missing])
        values[missing] = xyz[nearest, 2]
    return values.reshape(grid.shape).astype(np.float32)


def _set_barycentric_transforms(tin: Any) -> None:
    """Give scipy's ``Delaunay`` its barycentric transforms (cached in ``_transform``, which
    ``find_simplex`` and ``LinearNDInterpolator`` read) from :func:`_barycentric_transforms`.
    Should a scipy no longer cache them there, scipy computes them: with one BLAS thread,
    its thousands of 2x2 LAPACK calls being each 10x slower when they wake a thread pool on
    shared cores."""
    if getattr(tin, "_transform", False) is None:  # not computed yet
        tin._transform = _barycentric_transforms(tin.points, tin.simplices)
    else:  # pragma: no cover - another scipy
        with one_thread("blas"):
            tin.transform  # noqa: B018 - computed and cached


def _barycentric_transforms(
    points: NDArray[np.float64], simplices: NDArray[np.integer]
) -> NDArray[np.float64]:
    """scipy's ``Delaunay.transform`` of 2-D triangles, (triangles, 3, 2): ``T^-1`` and ``r``
    with ``T c = x - r``, ``T[i, j] = (vertex j - vertex 2)[i]``, ``r`` = vertex 2; NaN for
    the triangles scipy deems degenerate (reciprocal 1-norm condition under 1000 eps).
    The 2x2 inverse in closed form differs from LAPACK's by rounding only."""
    corners = points[simplices]
    r = corners[:, 2]
    a = corners[:, 0, 0] - r[:, 0]
    b = corners[:, 1, 0] - r[:, 0]
    c = corners[:, 0, 1] - r[:, 1]
    d = corners[:, 1, 1] - r[:, 1]
    det = a * d - b * c
    out = np.empty((len(simplices), 3, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        out[:, 0, 0] = d / det
        out[:, 0, 1] = -b / det
        out[:, 1, 0] = -c / det
        out[:, 1, 1] = a / det
        rcond = np.abs(det) / (
            np.maximum(np.abs(a) + np.abs(c), np.abs(b) + np.abs(d))
            * np.maximum(np.abs(d) + np.abs(c), np.abs(b) + np.abs(a))
        )
    out[:, 2] = r
    out[~(rcond >= 1000 * np.finfo(np.float64).eps)] = np.nan  # NaN rcond included
    return out


def _in_long_triangles(tin: Any, query: NDArray[np.float64], max_edge: float) -> NDArray[np.bool_]:
    """Which ``query`` points fall in a triangle of ``tin`` with an edge over ``max_edge``."""
    corners = tin.points[tin.simplices]  # (triangles, 3, 2)
    edges = corners - np.roll(corners, 1, axis=1)
    long = ((edges**2).sum(axis=2) > max_edge**2).any(axis=1)
    simplex = tin.find_simplex(query)
    return (simplex >= 0) & long[np.maximum(simplex, 0)]


def height_above_ground(
    points: PointsLike, dtm: NDArray[np.floating], grid: RasterGrid
) -> NDArray[np.float32]:
    """Height of each point above the DTM, bilinear between pixel centres (clamped at the edge
    half-pixel). Points outside the raster raise :class:`EnrichError`."""
    return _heights(as_xyz(points), dtm, grid, None)


def heights_and_pixels(
    points: PointsLike, dtm: NDArray[np.floating], grid: RasterGrid
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """:func:`height_above_ground`, and each point's pixel (:meth:`RasterGrid.flat_index`),
    found on the way (for rasters of the same points: :func:`chm_from_pixels`,
    :func:`density_from_pixels`)."""
    xyz = as_xyz(points)
    pixels = np.empty(len(xyz), dtype=np.int64)
    return _heights(xyz, dtm, grid, pixels), pixels


def _heights(
    xyz: NDArray[np.float64],
    dtm: NDArray[np.floating],
    grid: RasterGrid,
    pixels: NDArray[np.int64] | None,
) -> NDArray[np.float32]:
    """:func:`height_above_ground` of checked points; fills ``pixels`` when given."""
    if dtm.shape != grid.shape:
        raise EnrichError(f"DTM shape {dtm.shape} does not match the raster grid {grid.shape}")
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.float32)
    x, y = xyz[:, 0], xyz[:, 1]
    table = np.ascontiguousarray(np.asarray(dtm, dtype=np.float64)[::-1, :].T)  # south first
    if grid.ncols == 1 or grid.nrows == 1:  # degenerate axis: interpolate along the other only
        table = np.pad(table, ((0, grid.ncols == 1), (0, grid.nrows == 1)), mode="edge")
    heights = np.empty(len(xyz), dtype=np.float32)
    for rows in blocks(len(xyz)):  # blocks that stay in the CPU's cache
        # axis 0 = column index (x), axis 1 = row index counted from the south (y), in pixel
        # units from the first centre, clamped at the edge half-pixel
        u = grid._pixel_units(x[rows], grid.x0)
        v = grid._pixel_units(y[rows], grid.y0)
        # pixel units grow with the coordinates: the extremes tell whether any is outside
        if u.min() < 0 or u.max() >= grid.ncols or v.min() < 0 or v.max() >= grid.nrows:
            grid._flat_index(xyz)  # raises, counting the points outside
        if pixels is not None:  # as RasterGrid.flat_index: floor of the same pixel units
            pixel = pixels[rows]
            pixel[...] = np.floor(v)  # from the south
            np.subtract(grid.nrows - 1, pixel, out=pixel)
            pixel *= grid.ncols
            pixel += np.floor(u).astype(np.int64)
        u -= 0.5
        v -= 0.5
        np.clip(u, 0, grid.ncols - 1, out=u)
        np.clip(v, 0, grid.nrows - 1, out=v)
        ground_z = _bilinear(table, u, v)
        np.subtract(xyz[rows, 2], ground_z, out=ground_z)
        heights[rows] = ground_z
    if not np.isfinite(table).all():  # after the points' check: that error comes first
        raise EnrichError("the DTM has empty (non-finite) pixels")
    return heights


def _bilinear(
    table: NDArray[np.float64], u: NDArray[np.floating], v: NDArray[np.floating]
) -> NDArray[np.floating]:
    """Bilinear interpolation of ``table`` (values at pixel centres; ``u`` along axis 0,
    ``v`` along axis 1, in pixels from the first centre, >= 0; both overwritten) between
    the four centres around each point."""
    i = np.floor(u)
    np.minimum(i, table.shape[0] - 2, out=i)
    j = np.floor(v)
    np.minimum(j, table.shape[1] - 2, out=j)
    fu = np.subtract(u, i, out=u)
    fv = np.subtract(v, j, out=v)
    step = table.shape[1]  # (i + 1, j) is this far on from (i, j) in the flat table
    corner = i.astype(np.int64)
    corner *= step
    corner += j.astype(np.int64)
    values = table.ravel()
    gu = 1.0 - fu
    south = values.take(corner)
    south *= gu
    corner += step
    part = values.take(corner)  # (i + 1, j)
    part *= fu
    south += part
    corner += 1
    north = values.take(corner)  # (i + 1, j + 1)
    north *= fu
    corner -= step
    np.take(values, corner, out=part)  # (i, j + 1)
    part *= gu
    north += part
    south *= 1.0 - fv
    north *= fv
    south += north
    return south


def chm(
    points: PointsLike,
    heights: NDArray[np.floating],
    grid: RasterGrid,
    *,
    subcircle: float = 0.0,
    fill_empty: bool = True,
    fill_min_neighbours: int = FILL_MIN_NEIGHBOURS,
) -> NDArray[np.float32]:
    """Canopy height model: the highest height above ground per pixel (NaN = no point).

    ``heights`` are the points' heights above ground (e.g. :func:`height_above_ground`).
    Pit-free options: ``subcircle`` > 0 replaces each point by 8 points on a circle of that
    radius (lidR ``p2r(subcircle)``; only the highest point of each of the
    :data:`SUBPIXELS` x :data:`SUBPIXELS` sub-pixels is inflated, so the pixel maxima stay
    exact and a disc moves by at most a fifth of a pixel); ``fill_empty`` fills an empty
    pixel that has at least
    ``fill_min_neighbours`` (default :data:`FILL_MIN_NEIGHBOURS` = 6) of its 8 neighbours
    non-empty with their median (one pass, neighbours outside the raster count as empty): by
    default pits of one or two pixels are filled; larger canopy gaps (every pixel of a 2x2 or
    3x3 gap) and pixels beyond the data edge stay NaN.
    Negative heights are 0.
    """
    xyz = as_xyz(points)
    h = np.asarray(heights, dtype=np.float64)
    if h.shape != (len(xyz),):
        raise EnrichError(f"{h.shape} heights for {len(xyz)} points")
    top = _highest(grid._flat_index(xyz), h, grid)  # raises when a point is outside
    if subcircle > 0 and len(xyz):
        top = _inflate(top, xyz, h, grid, subcircle)
    return _canopy(top, grid, fill_empty, fill_min_neighbours)


def chm_from_pixels(
    pixels: NDArray[np.int64],
    heights: NDArray[np.floating],
    grid: RasterGrid,
    *,
    fill_empty: bool = True,
    fill_min_neighbours: int = FILL_MIN_NEIGHBOURS,
) -> NDArray[np.float32]:
    """:func:`chm` (without ``subcircle``) of points given by their pixels on ``grid``
    (:meth:`RasterGrid.flat_index`, e.g. from :func:`heights_and_pixels`); points whose
    height is NaN (no terrain) are left out."""
    h = np.asarray(heights)
    if h.dtype not in (np.float32, np.float64):
        h = h.astype(np.float64)
    if h.shape != pixels.shape:
        raise EnrichError(f"{h.shape} heights for {len(pixels)} points")
    pixels = _checked_pixels(pixels, grid)
    finite = np.isfinite(h)
    if not finite.all():
        pixels, h = pixels[finite], h[finite]
    # the highest float32 height is the highest in float64 too: the CHM is the same
    top = _highest(pixels, h, grid).astype(np.float64, copy=False)
    return _canopy(top, grid, fill_empty, fill_min_neighbours)


def _checked_pixels(pixels: NDArray[np.int64], grid: RasterGrid) -> NDArray[np.int64]:
    """``pixels`` (flat indices), checked to lie on ``grid``."""
    pixels = np.asarray(pixels)
    if pixels.dtype != np.int64 or pixels.ndim != 1:
        raise EnrichError(f"pixel indices must be a 1-D int64 array, got {pixels.dtype}")
    # as unsigned, a negative index is huge: one maximum tells if any is outside
    if len(pixels) and int(pixels.view(np.uint64).max()) >= grid.nrows * grid.ncols:
        raise EnrichError(f"pixel indices outside the raster of shape {grid.shape}")
    return pixels


def _highest(
    pixels: NDArray[np.int64], h: NDArray[np.floating], grid: RasterGrid
) -> NDArray[np.floating]:
    """The highest ``h`` per pixel, flat, of ``h``'s dtype (-inf where no point)."""
    top = np.full(grid.nrows * grid.ncols, -np.inf, dtype=h.dtype)
    np.maximum.at(top, pixels, h)
    return top


def _canopy(
    top: NDArray[np.floating], grid: RasterGrid, fill_empty: bool, fill_min_neighbours: int
) -> NDArray[np.float32]:
    """The CHM from the highest height per pixel (flat, -inf where no point)."""
    top[np.isneginf(top)] = np.nan
    out = np.maximum(top.reshape(grid.shape), 0.0)
    if not 1 <= fill_min_neighbours <= 8:
        raise EnrichError(f"fill_min_neighbours must be 1..8, got {fill_min_neighbours}")
    if fill_empty:
        out = _fill_isolated(out, fill_min_neighbours)
    return out.astype(np.float32)


#: Sub-pixels per pixel side among which only the highest point is inflated (``subcircle``).
SUBPIXELS = 5


def _inflate(
    top: NDArray[np.floating],
    xyz: NDArray[np.float64],
    h: NDArray[np.float64],
    grid: RasterGrid,
    subcircle: float,
) -> NDArray[np.float64]:
    """``top`` (flat, on ``grid``) raised by 8 points on a circle of radius ``subcircle``
    around each point highest in its sub-pixel."""
    x, y, h = _highest_per_subpixel(xyz[:, 0], xyz[:, 1], h, grid, SUBPIXELS)
    # a margin of pixels around the raster takes the circle points outside it (cut off at
    # the end): no mask of the inside points per angle
    margin = math.ceil(subcircle / grid.pixel_size) + 1
    width = grid.ncols + 2 * margin
    padded = np.full((grid.nrows + 2 * margin, width), -np.inf)
    inner = (slice(margin, margin + grid.nrows), slice(margin, margin + grid.ncols))
    padded[inner] = top.reshape(grid.shape)
    flat = padded.ravel()
    index = np.empty(min(len(x), BLOCK), dtype=np.int64)
    for angle in np.arange(8) * (np.pi / 4):
        dx, dy = subcircle * np.cos(angle), subcircle * np.sin(angle)
        for part in blocks(len(x)):  # in the points' order, as one call per angle would
            n = part.stop - part.start
            shifted = x[part] + dx
            index[:n] = grid._pixel_floor(shifted, grid.x0)  # column
            index[:n] += margin
            np.add(y[part], dy, out=shifted)
            row = grid._pixel_floor(shifted, grid.y0)  # row from the south
            np.subtract(grid.nrows - 1 + margin, row, out=row)
            row *= width
            index[:n] += row.astype(np.int64)
            np.maximum.at(flat, index[:n], h[part])
    return padded[inner].ravel()


def _highest_per_subpixel(
    x: NDArray[np.float64], y: NDArray[np.float64], h: NDArray[np.float64], grid: RasterGrid, n: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """x, y and h of the points highest in their sub-pixel (``n`` x ``n`` per pixel of
    ``grid``)."""
    step = grid.pixel_size / n
    cols, rows = grid.ncols * n, grid.nrows * n
    index = np.empty(len(x), dtype=np.int64)
    for part in blocks(len(x)):  # blocks that stay in the CPU's cache
        units = x[part] - grid.x0
        units /= step
        col = np.clip(np.floor(units, out=units).astype(np.int64), 0, cols - 1)
        units = y[part] - grid.y0
        units /= step
        row = index[part]
        np.clip(np.floor(units, out=units).astype(np.int64), 0, rows - 1, out=row)
        row *= cols
        row += col
    top = np.full(rows * cols, -np.inf)
    np.maximum.at(top, index, h)
    keep = np.flatnonzero(h >= top[index])
    return x[keep], y[keep], h[keep]


def _fill_isolated(raster: NDArray[np.float64], min_neighbours: int) -> NDArray[np.float64]:
    """Fill each NaN pixel having >= ``min_neighbours`` finite pixels among its 8
    neighbours with their median; other NaN pixels stay NaN."""
    empty = ~np.isfinite(raster)
    if not empty.any():
        return raster
    padded = np.pad(raster, 1, constant_values=np.nan)
    rows, cols = np.nonzero(empty)
    stack = np.stack(
        [padded[rows + dr, cols + dc] for dr in range(3) for dc in range(3) if (dr, dc) != (1, 1)]
    )
    enough = np.isfinite(stack).sum(axis=0) >= min_neighbours
    out = raster.copy()
    if enough.any():
        out[rows[enough], cols[enough]] = np.nanmedian(stack[:, enough], axis=0)
    return out


def density(points: PointsLike, grid: RasterGrid) -> NDArray[np.float32]:
    """Points per m2 in each pixel (0 where a pixel of the raster has no point)."""
    return density_from_pixels(grid._flat_index(as_xyz(points)), grid)


def density_from_pixels(pixels: NDArray[np.int64], grid: RasterGrid) -> NDArray[np.float32]:
    """:func:`density` of points given by their pixels on ``grid``
    (:meth:`RasterGrid.flat_index`)."""
    counts = pixel_counts(pixels, grid)
    return (counts / grid.pixel_size**2).astype(np.float32)


def pixel_counts(pixels: NDArray[np.int64], grid: RasterGrid) -> NDArray[np.int64]:
    """Points per pixel of ``grid``, from their pixels (:meth:`RasterGrid.flat_index`)."""
    counts = np.bincount(_checked_pixels(pixels, grid), minlength=grid.nrows * grid.ncols)
    return counts.astype(np.int64, copy=False).reshape(grid.shape)
