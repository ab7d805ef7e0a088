"""Observed ground: where a survey saw the ground, as a mask pixel-aligned to the stand grid.

A pixel (default 1 m) is **observed** when ground returns were recorded in it, or when it
lies in a gap narrower than about twice ``closing_radius`` between observed pixels (a
morphological closing: the ground under a stem, or between two scan lines, is hidden by
the stem or the sampling, not unsurveyed). Closing never grows the outer edge of the
survey, and the mask is cut to the catalog's cells. A stand's observed area is its observed
pixels' squares clipped to its polygon (:func:`polygon_mask_area`). Per-hectare values divide
by the observed area and count only trees whose stem stands in it; change uses the pixels
observed in both epochs. A pixel is **near ground** when a ground return lies within
``closing_radius`` of it: the DTM and the CHM are written only there (elsewhere the
terrain, and so every height above it, is an extrapolation).
Definitions and defaults: docs/METRICS.md ("Observed area").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid.errors import EnrichError
from standgrid.rastergrid import RasterGrid

#: Gaps in the ground returns up to about twice this radius are closed (m).
CLOSING_RADIUS_M = 2.0
#: The mask's no-data value (outside every cell) in ``observed.tif``.
MASK_NODATA = 255


@dataclass(frozen=True)
class Coverage:
    """One epoch's coverage rasters on ``grid``: observed pixels, pixels near ground, cells."""

    grid: RasterGrid
    observed: NDArray[np.bool_]
    near_ground: NDArray[np.bool_]
    in_cells: NDArray[np.bool_]

    def as_mask_raster(self) -> NDArray[np.uint8]:
        """1 observed, 0 not observed, :data:`MASK_NODATA` outside the cells."""
        out = np.where(self.observed, 1, 0).astype(np.uint8)
        out[~self.in_cells] = MASK_NODATA
        return out

    def observed_at(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether each position lies on an observed pixel (False outside the raster)."""
        return sample_mask(self.observed, self.grid, x, y)

    def observed_in(self, pixels: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Whether each pixel (:meth:`RasterGrid.flat_index` on ``grid``) is observed."""
        return np.take(self.observed, pixels)

    def observed_m2(self, polygon: Any) -> float:
        """Observed area inside ``polygon`` (m²): :func:`polygon_mask_area` of the mask."""
        return polygon_mask_area(self.observed, self.grid, polygon)


def ground_hits(grid: RasterGrid, ground_xy: NDArray[np.float64]) -> NDArray[np.int64]:
    """Ground returns per pixel of ``grid`` (points outside it are ignored)."""
    counts = np.zeros(grid.nrows * grid.ncols, dtype=np.int64)
    if len(ground_xy):
        row, col = grid.pixel_of(ground_xy[:, 0], ground_xy[:, 1])
        inside = (row >= 0) & (row < grid.nrows) & (col >= 0) & (col < grid.ncols)
        np.add.at(counts, row[inside] * grid.ncols + col[inside], 1)
    return counts.reshape(grid.shape)


def coverage_from_hits(
    hits: NDArray[np.integer],
    grid: RasterGrid,
    in_cells: NDArray[np.bool_],
    *,
    closing_radius: float = CLOSING_RADIUS_M,
    min_ground_returns: int = 1,
) -> Coverage:
    """The observed and near-ground masks from the ground returns per pixel."""
    from scipy import ndimage

    if hits.shape != grid.shape or in_cells.shape != grid.shape:
        raise EnrichError(f"coverage rasters {hits.shape}, {in_cells.shape} != grid {grid.shape}")
    if closing_radius < 0 or min_ground_returns < 1:
        raise EnrichError(
            f"closing radius {closing_radius} must be >= 0 and min ground returns "
            f"{min_ground_returns} >= 1"
        )
    seen = np.asarray(hits) >= min_ground_returns
    ps = grid.pixel_size
    pad = math.ceil(closing_radius / ps) + 1
    padded = np.pad(seen, pad, constant_values=False)
    # dilation by the radius (distance to the nearest seen pixel), then erosion by it
    if padded.any():
        near = ndimage.distance_transform_edt(~padded) * ps <= closing_radius + 1e-9
    else:
        near = np.zeros_like(padded)
    closed = ndimage.distance_transform_edt(near) * ps > closing_radius + 1e-9
    crop = (slice(pad, pad + grid.nrows), slice(pad, pad + grid.ncols))
    observed = (closed[crop] | seen) & in_cells
    return Coverage(grid, observed, near[crop] & in_cells, in_cells.copy())


def cells_mask(grid: RasterGrid, polygons: list[Any]) -> NDArray[np.bool_]:
    """Pixels whose centre lies in one of ``polygons``."""
    from rasterio import features

    if not polygons:
        return np.zeros(grid.shape, dtype=bool)
    return features.geometry_mask(
        polygons, out_shape=grid.shape, transform=grid.transform, invert=True
    )


def sample_mask(mask: NDArray[np.bool_], grid: RasterGrid, x: Any, y: Any) -> NDArray[np.bool_]:
    """``mask`` at each (x, y); False outside the raster."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    out = np.zeros(len(x), dtype=bool)
    finite = np.isfinite(x) & np.isfinite(y)
    row, col = grid.pixel_of(np.where(finite, x, grid.x0), np.where(finite, y, grid.y0))
    inside = finite & (row >= 0) & (row < grid.nrows) & (col >= 0) & (col < grid.ncols)
    out[inside] = mask[row[inside], col[inside]]
    return out


def window(grid: RasterGrid, polygon: Any) -> tuple[RasterGrid, tuple[slice, slice]]:
    """The pixels of ``grid`` covering ``polygon``'s bounds, and their slice of the array."""
    pixels = grid.window(polygon.bounds)
    r0, c0 = int(pixels.row_off), int(pixels.col_off)  # row 0 is the northern edge
    rows, cols = slice(r0, r0 + int(pixels.height)), slice(c0, c0 + int(pixels.width))
    return grid.window_grid(pixels), (rows, cols)


def polygon_mask_area(mask: NDArray[np.bool_], grid: RasterGrid, polygon: Any) -> float:
    """Area (m²) of the set pixels of ``mask`` inside ``polygon``: each set pixel's square
    clipped to the polygon (exact to float rounding, ~1e-9 m²; never above the polygon's
    area). A rectangle on the pixel lattice (a grid cell) is its set pixels × pixel area;
    otherwise pixels the polygon covers whole count their full area and only those its edge
    crosses are intersected."""
    import shapely

    sub, index = window(grid, polygon)
    set_pixels = mask[index]
    ps = grid.pixel_size
    if _on_lattice(polygon, sub):  # the window is exactly the polygon's pixels
        return float(np.count_nonzero(set_pixels)) * ps**2
    rows, cols = np.nonzero(set_pixels)
    if not len(rows):
        return 0.0
    xmin = sub.x0 + cols * ps
    ymin = sub.y0 + (sub.nrows - 1 - rows) * ps  # row 0 is the northern edge
    squares = shapely.box(xmin, ymin, xmin + ps, ymin + ps)
    shapely.prepare(polygon)
    whole = shapely.covers(polygon, squares)
    edge = ~whole & shapely.intersects(polygon, squares)
    partial = shapely.area(shapely.intersection(squares[edge], polygon))
    area = float(np.count_nonzero(whole)) * ps**2 + float(partial.sum())
    return min(area, float(polygon.area))  # a fully observed polygon: its area, not + 1e-12


def _on_lattice(polygon: Any, sub: RasterGrid) -> bool:
    """Whether ``polygon`` is the rectangle of the pixels of ``sub`` (to 1e-9 pixel)."""
    if (
        polygon.geom_type != "Polygon"
        or len(polygon.interiors)
        or not polygon.equals(polygon.envelope)
    ):
        return False
    tol = 1e-9 * sub.pixel_size
    return bool(np.allclose(polygon.bounds, sub.bounds, rtol=0.0, atol=tol))
