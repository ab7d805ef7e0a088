"""A raster's pixel grid as a value: origin, pixel size, shape and CRS, with windows.

A :class:`RasterGrid` is the one raster grid of standgrid (enrich's terrain and canopy
rasters, compare's differences): north-up square pixels, its CRS carried
(:class:`~standgrid.crs.CRS`), a window of it (rasterio's ``Window``: row 0 north) for a
bbox, and a window's own grid. Coordinates are float64 x/y.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.crs import CRS, CRSLike
from standgrid.errors import EnrichError, GridError

if TYPE_CHECKING:
    from rasterio.windows import Window

_TOL = 1e-9
#: Points per block of the pixel lookups (blocks that stay in the CPU's cache).
BLOCK = 1 << 16


@dataclass(frozen=True)
class RasterGrid:
    """``ncols`` x ``nrows`` pixels of ``pixel_size`` m; lower-left corner ``(x0, y0)``, in
    ``crs`` (None: local coordinates). Row 0 is the northern row (GeoTIFF order)."""

    x0: float
    y0: float
    pixel_size: float
    ncols: int
    nrows: int
    crs: CRS | None = None

    def __post_init__(self) -> None:
        if self.crs is not None and not isinstance(self.crs, CRS):
            object.__setattr__(self, "crs", CRS.of(self.crs))

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
        crs: CRSLike | None = None,
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
            crs=None if crs is None else CRS.of(crs),
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

    # --- windows ------------------------------------------------------------------------

    def window(self, bounds: tuple[float, float, float, float], *, clip: bool = True) -> Window:
        """The pixels covering ``bounds`` = (xmin, ymin, xmax, ymax) (at least one; edges
        within 1e-9 pixel of a pixel edge count as on it), clipped to the grid unless
        ``clip`` is False (a window of the grid's lattice, possibly beyond it)."""
        from rasterio.windows import Window

        xmin, ymin, xmax, ymax = bounds
        ps = self.pixel_size
        i0 = math.floor((xmin - self.x0) / ps + _TOL)
        i1 = math.ceil((xmax - self.x0) / ps - _TOL)
        j0 = math.floor((ymin - self.y0) / ps + _TOL)
        j1 = math.ceil((ymax - self.y0) / ps - _TOL)
        if clip:
            i0, i1 = max(0, i0), min(self.ncols, i1)
            j0, j1 = max(0, j0), min(self.nrows, j1)
        i1, j1 = max(i1, i0 + 1), max(j1, j0 + 1)
        return Window(i0, self.nrows - j1, i1 - i0, j1 - j0)  # rows from the north

    def window_grid(self, window: Window) -> RasterGrid:
        """The grid of a :meth:`window`'s pixels (same pixel size and CRS)."""
        ps = self.pixel_size
        i0, width, height = int(window.col_off), int(window.width), int(window.height)
        j0 = self.nrows - int(window.row_off) - height  # rows from the south
        return RasterGrid(self.x0 + i0 * ps, self.y0 + j0 * ps, ps, width, height, self.crs)

    @property
    def transform(self) -> Any:
        """The ``Affine`` transform rasterio takes (north-up)."""
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
        for part in blocks(len(x)):  # blocks that stay in the CPU's cache
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
        col = np.empty(min(len(x), BLOCK), dtype=np.int64)
        outside = False
        for part in blocks(len(x)):  # blocks that stay in the CPU's cache
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


def blocks(n: int) -> list[slice]:
    """Slices of ``n`` rows in blocks of :data:`BLOCK`."""
    return [slice(start, min(start + BLOCK, n)) for start in range(0, n, BLOCK)]
