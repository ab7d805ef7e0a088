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
        col = np.floor(self._pixel_units(x, self.x0)).astype(np.int64)
        row_from_south = np.floor(self._pixel_units(y, self.y0)).astype(np.int64)
        return self.nrows - 1 - row_from_south, col

    def _pixel_units(self, values: NDArray[np.floating], origin: float) -> NDArray[np.floating]:
        """(values - origin) / pixel_size (a new array): pixel units from the corner."""
        units = np.asarray(values) - origin
        units /= self.pixel_size
        return units

    def centers(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixel-centre coordinates, each of ``shape``."""
        xs = self.x0 + (np.arange(self.ncols) + 0.5) * self.pixel_size
        ys = self.bounds[3] - (np.arange(self.nrows) + 0.5) * self.pixel_size
        return np.meshgrid(xs, ys)

    def _flat_index(self, xyz: NDArray[np.float64]) -> NDArray[np.int64]:
        row, col = self.pixel_of(xyz[:, 0], xyz[:, 1])
        if len(row) and (
            row.min() < 0 or row.max() >= self.nrows or col.min() < 0 or col.max() >= self.ncols
        ):
            outside = (row < 0) | (row >= self.nrows) | (col < 0) | (col >= self.ncols)
            raise EnrichError(
                f"{int(outside.sum())} of {len(xyz)} points fall outside the raster {self.bounds}"
            )
        row *= self.ncols
        row += col
        return row


def dtm_from_ground(
    ground: PointsLike, grid: RasterGrid, *, max_edge: float | None = None
) -> NDArray[np.float32]:
    """Digital terrain model: Delaunay (TIN) linear interpolation of the ground points at pixel
    centres, nearest ground point outside their convex hull and, given ``max_edge`` (m, as
    lidR's ``tin(max_edge=)``), inside triangles with a longer edge: a pixel's value then
    depends only on the ground within ``max_edge`` of it (or, past that, on the nearest),
    not on how far the survey's hull reaches."""
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
        # one BLAS thread: the triangles' barycentric transforms are thousands of 2x2
        # LAPACK calls, each 10x slower when it wakes a thread pool on shared cores
        with contextlib.suppress(QhullError), one_thread("blas"):  # collinear: nearest below
            tin = Delaunay(local)
            values = LinearNDInterpolator(tin, xyz[:, 2])(query)
            if max_edge is not None:
                values[_in_long_triangles(tin, query, max_edge)] = np.nan
    missing = ~np.isfinite(values)
    if missing.any():
        _, nearest = cKDTree(local).query(query[missing])
        values[missing] = xyz[nearest, 2]
    return values.reshape(grid.shape).astype(np.float32)


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
    xyz = as_xyz(points)
    if dtm.shape != grid.shape:
        raise EnrichError(f"DTM shape {dtm.shape} does not match the raster grid {grid.shape}")
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.float32)
    x, y = xyz[:, 0], xyz[:, 1]
    # pixel units grow with the coordinates: the extreme points tell whether any is outside
    u_range = grid._pixel_units(np.array([x.min(), x.max()]), grid.x0)
    v_range = grid._pixel_units(np.array([y.min(), y.max()]), grid.y0)
    if u_range[0] < 0 or u_range[1] >= grid.ncols or v_range[0] < 0 or v_range[1] >= grid.nrows:
        grid._flat_index(xyz)  # raises, counting the points outside
    table = np.ascontiguousarray(np.asarray(dtm, dtype=np.float64)[::-1, :].T)  # south first
    if not np.isfinite(table).all():
        raise EnrichError("the DTM has empty (non-finite) pixels")
    if grid.ncols == 1 or grid.nrows == 1:  # degenerate axis: interpolate along the other only
        table = np.pad(table, ((0, grid.ncols == 1), (0, grid.nrows == 1)), mode="edge")
    heights = np.empty(len(xyz), dtype=np.float32)
    for start in range(0, len(xyz), _BLOCK):  # blocks that stay in the CPU's cache
        rows = slice(start, start + _BLOCK)
        # axis 0 = column index (x), axis 1 = row index counted from the south (y), in pixel
        # units from the first centre, clamped at the edge half-pixel
        u = grid._pixel_units(x[rows], grid.x0)
        u -= 0.5
        v = grid._pixel_units(y[rows], grid.y0)
        v -= 0.5
        ground_z = _bilinear(table, np.clip(u, 0, grid.ncols - 1), np.clip(v, 0, grid.nrows - 1))
        np.subtract(xyz[rows, 2], ground_z, out=ground_z)
        heights[rows] = ground_z
    return heights


#: Points per block of the element-wise arithmetic of :func:`height_above_ground`.
_BLOCK = 1 << 16


def _bilinear(
    table: NDArray[np.float64], u: NDArray[np.float64], v: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Bilinear interpolation of ``table`` (values at pixel centres; ``u`` along axis 0,
    ``v`` along axis 1, in pixels from the first centre) between the four centres around
    each point."""
    i = np.minimum(np.floor(u).astype(np.int64), table.shape[0] - 2)
    j = np.minimum(np.floor(v).astype(np.int64), table.shape[1] - 2)
    fu, fv = u - i, v - j
    step = table.shape[1]  # (i + 1, j) is this far on from (i, j) in the flat table
    corner = i * step + j
    values = table.ravel()
    gu = 1.0 - fu
    south = gu * values[corner]
    south += fu * values[corner + step]
    north = gu * values[corner + 1]
    north += fu * values[corner + (step + 1)]
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
    xy = xyz[:, :2]
    index = grid._flat_index(xyz)  # raises when a point is outside the raster
    top = np.full(grid.nrows * grid.ncols, -np.inf)
    np.maximum.at(top, index, h)
    if subcircle > 0 and len(xy):
        xy, h = _highest_per_subpixel(xy, h, grid, SUBPIXELS)
        for angle in np.arange(8) * (np.pi / 4):
            x = xy[:, 0] + subcircle * np.cos(angle)
            y = xy[:, 1] + subcircle * np.sin(angle)
            row, col = grid.pixel_of(x, y)
            inside = (row >= 0) & (row < grid.nrows) & (col >= 0) & (col < grid.ncols)
            np.maximum.at(top, row[inside] * grid.ncols + col[inside], h[inside])
    top[np.isneginf(top)] = np.nan
    out = np.maximum(top.reshape(grid.shape), 0.0)
    if not 1 <= fill_min_neighbours <= 8:
        raise EnrichError(f"fill_min_neighbours must be 1..8, got {fill_min_neighbours}")
    if fill_empty:
        out = _fill_isolated(out, fill_min_neighbours)
    return out.astype(np.float32)


#: Sub-pixels per pixel side among which only the highest point is inflated (``subcircle``).
SUBPIXELS = 5


def _highest_per_subpixel(
    xy: NDArray[np.float64], h: NDArray[np.float64], grid: RasterGrid, n: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The points that are highest in their sub-pixel (``n`` x ``n`` per pixel of ``grid``)."""
    step = grid.pixel_size / n
    cols, rows = grid.ncols * n, grid.nrows * n
    col = np.clip(np.floor((xy[:, 0] - grid.x0) / step).astype(np.int64), 0, cols - 1)
    row = np.clip(np.floor((xy[:, 1] - grid.y0) / step).astype(np.int64), 0, rows - 1)
    index = row * cols + col
    top = np.full(rows * cols, -np.inf)
    np.maximum.at(top, index, h)
    keep = h >= top[index]
    return xy[keep], h[keep]


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
    xyz = as_xyz(points)
    counts = np.bincount(grid._flat_index(xyz), minlength=grid.nrows * grid.ncols)
    return (counts / grid.pixel_size**2).reshape(grid.shape).astype(np.float32)


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
