"""Terrain and canopy rasters pixel-aligned to the stand grid, written as Cloud-Optimized GeoTIFFs.

A :class:`RasterGrid` is a pixel lattice whose pixel size divides the stand cell size and whose
corner lies on the stand grid origin plus an integer number of pixels, so rasters of every epoch
(and every stand cell) overlay pixel for pixel. Row 0 is the northern row (GeoTIFF order).
"""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from standgrid._atomic import atomic_output
from standgrid.enrich.ground import PointsLike, as_xyz, one_thread
from standgrid.errors import EnrichError, FormatError, GridError

_TOL = 1e-9
#: The no-data value of every raster standgrid writes (DTM, CHM, density, CHM change).
NODATA = -9999.0
#: An empty CHM pixel is filled when at least this many of its 8 neighbours hold a height.
FILL_MIN_NEIGHBOURS = 6


@dataclass(frozen=True)
class RasterGrid:
    """``ncols`` x ``nrows`` pixels of ``pixel_size`` m; lower-left corner ``(x0, y0)``."""

    x0: float
    y0: float
    pixel_size: float
    ncols: int
    nrows: int

    @classmethod
    def covering(
        cls,
        bounds: tuple[float, float, float, float],
        *,
        origin: tuple[float, float],
        cell_size: float,
        pixel_size: float = 1.0,
        snap_to_cells: bool = True,
        closed: bool = False,
    ) -> RasterGrid:
        """The aligned raster covering ``bounds`` = (xmin, ymin, xmax, ymax).

        ``origin`` and ``cell_size`` are the stand grid's; ``pixel_size`` must divide
        ``cell_size``. With ``snap_to_cells`` the extent grows to whole stand cells. Bounds
        are of points (half-open: a point at ``xmax`` is inside) unless ``closed``: the
        bounds of polygons, so cells whose upper edge is ``xmax`` end the raster there.
        """
        if pixel_size <= 0 or cell_size <= 0:
            raise GridError(f"pixel size {pixel_size} and cell size {cell_size} must be > 0")
        ratio = cell_size / pixel_size
        if abs(ratio - round(ratio)) > 1e-6:
            raise GridError(
                f"pixel size {pixel_size} m does not divide the cell size {cell_size} m"
            )
        xmin, ymin, xmax, ymax = (float(v) for v in bounds)
        if not (np.isfinite([xmin, ymin, xmax, ymax]).all() and xmax >= xmin and ymax >= ymin):
            raise GridError(f"invalid bounds {bounds}")
        step = cell_size if snap_to_cells else pixel_size
        ox, oy = float(origin[0]), float(origin[1])
        i0 = math.floor((xmin - ox) / step + _TOL)
        j0 = math.floor((ymin - oy) / step + _TOL)
        if closed:  # the bounds of polygons: an upper edge on the lattice ends the raster
            i1 = max(math.ceil((xmax - ox) / step - _TOL), i0 + 1)
            j1 = max(math.ceil((ymax - oy) / step - _TOL), j0 + 1)
        else:  # half-open: a point at xmax must be inside
            i1 = max(math.floor((xmax - ox) / step + _TOL) + 1, i0 + 1)
            j1 = max(math.floor((ymax - oy) / step + _TOL) + 1, j0 + 1)
        per = round(step / pixel_size)
        return cls(
            x0=ox + i0 * step,
            y0=oy + j0 * step,
            pixel_size=float(pixel_size),
            ncols=(i1 - i0) * per,
            nrows=(j1 - j0) * per,
        )

    @property
    def shape(self) -> tuple[int, int]:
        return (self.nrows, self.ncols)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return (
            self.x0,
            self.y0,
            self.x0 + self.ncols * self.pixel_size,
            self.y0 + self.nrows * self.pixel_size,
        )

    @property
    def transform(self) -> Any:
        """The rasterio ``Affine`` (north-up)."""
        from affine import Affine

        return Affine(self.pixel_size, 0.0, self.x0, 0.0, -self.pixel_size, self.bounds[3])

    def pixel_of(
        self, x: NDArray[np.float64], y: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """(row, col) of the pixel containing each point (may be outside ``shape``)."""
        x, y = np.asarray(x), np.asarray(y)
        if x.ndim != 1 or y.shape != x.shape:
            col = np.floor(self._pixel_units(x, self.x0)).astype(np.int64)
            row_from_south = np.floor(self._pixel_units(y, self.y0)).astype(np.int64)
            return self.nrows - 1 - row_from_south, col
        row, col = np.empty(len(x), dtype=np.int64), np.empty(len(x), dtype=np.int64)
        for part in _blocks(len(x)):  # blocks that stay in the CPU's cache
            col[part] = self._pixel_floor(x[part], self.x0)
            row[part] = self._pixel_floor(y[part], self.y0)  # from the south, for now
            np.subtract(self.nrows - 1, row[part], out=row[part])
        return row, col

    def _pixel_units(self, values: NDArray[np.floating], origin: float) -> NDArray[np.floating]:
        """(values - origin) / pixel_size (a new array): pixel units from the corner."""
        units = np.asarray(values) - origin
        units /= self.pixel_size
        return units

    def _pixel_floor(self, values: NDArray[np.floating], origin: float) -> NDArray[np.floating]:
        """floor((values - origin) / pixel_size) (a new float array): the pixel index."""
        units = self._pixel_units(values, origin)
        return np.floor(units, out=units)

    def flat_index(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.int64]:
        """Each point's pixel as ``row * ncols + col``; points outside the raster raise
        :class:`EnrichError`."""
        x, y = np.asarray(x), np.asarray(y)
        index = np.empty(len(x), dtype=np.int64)
        col = np.empty(min(len(x), _BLOCK), dtype=np.int64)
        outside = False
        for part in _blocks(len(x)):  # blocks that stay in the CPU's cache
            n = part.stop - part.start
            col[:n] = self._pixel_floor(x[part], self.x0)
            row = index[part]
            row[...] = self._pixel_floor(y[part], self.y0)  # from the south, for now
            # as unsigned, a negative index is huge: one maximum tells if any is outside
            outside |= int(col[:n].view(np.uint64).max()) >= self.ncols
            outside |= int(row.view(np.uint64).max()) >= self.nrows
            np.subtract(self.nrows - 1, row, out=row)
            row *= self.ncols
            row += col[:n]
        if outside:
            row_of, col_of = self.pixel_of(x, y)
            out = (row_of < 0) | (row_of >= self.nrows) | (col_of < 0) | (col_of >= self.ncols)
            raise EnrichError(
                f"{int(out.sum())} of {len(x)} points fall outside the raster {self.bounds}"
            )
        return index

    def centers(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixel-centre coordinates, each of ``shape``."""
        xs = self.x0 + (np.arange(self.ncols) + 0.5) * self.pixel_size
        ys = self.bounds[3] - (np.arange(self.nrows) + 0.5) * self.pixel_size
        return np.meshgrid(xs, ys)

    def _flat_index(self, xyz: NDArray[np.float64]) -> NDArray[np.int64]:
        return self.flat_index(xyz[:, 0], xyz[:, 1])


def _blocks(n: int) -> list[slice]:
    """Slices of ``n`` rows in blocks of :data:`_BLOCK`."""
    return [slice(start, min(start + _BLOCK, n)) for start in range(0, n, _BLOCK)]


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
    for rows in _blocks(len(xyz)):  # blocks that stay in the CPU's cache
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


#: Points per block of element-wise arithmetic over many points.
_BLOCK = 1 << 16


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
    index = np.empty(min(len(x), _BLOCK), dtype=np.int64)
    for angle in np.arange(8) * (np.pi / 4):
        dx, dy = subcircle * np.cos(angle), subcircle * np.sin(angle)
        for part in _blocks(len(x)):  # in the points' order, as one call per angle would
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
    for part in _blocks(len(x)):  # blocks that stay in the CPU's cache
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


def write_cog(
    path: str | os.PathLike[str],
    array: NDArray[np.generic],
    grid: RasterGrid,
    *,
    crs: str | None,
    nodata: float | None = None,
    description: str | None = None,
    overwrite: bool = True,
    blocksize: int = 256,
) -> None:
    """Write one band as a Cloud-Optimized GeoTIFF (deflate, tiled, overviews), atomically.

    NaN pixels are written as ``nodata`` when given (NaN is the nodata of float rasters
    by default). ``crs`` is ``EPSG:XXXX`` or WKT2 (``None`` for local coordinates).
    """
    import rasterio
    from rasterio.io import MemoryFile
    from rasterio.shutil import copy as rio_copy

    data = np.asarray(array)
    if data.shape != grid.shape:
        raise EnrichError(f"array shape {data.shape} does not match the raster grid {grid.shape}")
    if nodata is None and np.issubdtype(data.dtype, np.floating):
        nodata = float("nan")
    if nodata is not None and not math.isnan(nodata):
        data = np.where(np.isnan(data), nodata, data).astype(data.dtype)
    profile: dict[str, Any] = {
        "driver": "GTiff",
        "width": grid.ncols,
        "height": grid.nrows,
        "count": 1,
        "dtype": data.dtype.name,
        "transform": grid.transform,
        "nodata": nodata,
    }
    if crs is not None:
        profile["crs"] = rasterio.crs.CRS.from_user_input(crs)
    with atomic_output(path, overwrite=overwrite) as tmp, MemoryFile() as mem:
        with mem.open(**profile) as ds:
            ds.write(data, 1)
            if description:
                ds.set_band_description(1, description)
                ds.update_tags(DESCRIPTION=description)
        with mem.open() as src:
            with rasterio.Env() as env:
                has_cog = "COG" in env.drivers()
            if has_cog:
                rio_copy(
                    src,
                    str(tmp),
                    driver="COG",
                    COMPRESS="DEFLATE",
                    BLOCKSIZE=blocksize,
                    OVERVIEWS="AUTO",
                    RESAMPLING="AVERAGE",
                )
            else:  # pragma: no cover - GDAL < 3.1
                _write_cog_fallback(src, str(tmp), blocksize)


def _write_cog_fallback(src: Any, target: str, blocksize: int) -> None:  # pragma: no cover
    """Tiled deflate GeoTIFF with internal overviews, for GDAL without the COG driver."""
    from rasterio.enums import Resampling
    from rasterio.io import MemoryFile
    from rasterio.shutil import copy as rio_copy

    profile = src.profile | {"tiled": True, "blockxsize": blocksize, "blockysize": blocksize}
    with MemoryFile() as mem, mem.open(**profile) as staged:
        staged.write(src.read())
        factors = [f for f in (2, 4, 8, 16, 32) if min(src.width, src.height) // f >= 1]
        if factors:
            staged.build_overviews(factors, Resampling.average)
        rio_copy(
            staged,
            target,
            driver="GTiff",
            tiled=True,
            blockxsize=blocksize,
            blockysize=blocksize,
            compress="deflate",
            COPY_SRC_OVERVIEWS="YES",
        )


class RasterData(NamedTuple):
    """A single-band raster read back: values (NaN for nodata), its grid, CRS text, description."""

    array: NDArray[np.float64]
    grid: RasterGrid
    crs: str | None
    description: str | None


def read_raster(path: str | os.PathLike[str]) -> RasterData:
    """Read a north-up single-band raster written by :func:`write_cog` (nodata -> NaN)."""
    import rasterio
    from rasterio.errors import RasterioIOError

    try:
        with rasterio.open(path) as ds:
            t = ds.transform
            if t.b != 0 or t.d != 0 or t.e != -t.a:
                raise FormatError("not a north-up raster with square pixels", path=path)
            data = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
            grid = RasterGrid(
                x0=t.c, y0=t.f + t.e * ds.height, pixel_size=t.a, ncols=ds.width, nrows=ds.height
            )
            crs = raster_crs_text(ds.crs)
            description = ds.descriptions[0] if ds.descriptions else None
    except RasterioIOError as exc:
        raise FormatError(f"cannot read raster: {exc}", path=path) from exc
    return RasterData(data, grid, crs, description)


def raster_crs_text(crs: Any) -> str | None:
    """A rasterio CRS as standgrid stores CRSs (EPSG:XXXX or WKT2); None for no CRS."""
    if not crs:
        return None
    import pyproj

    from standgrid.georeference.crs import crs_to_text

    return crs_to_text(pyproj.CRS.from_wkt(crs.to_wkt()))
