"""Canopy height change: the difference of two CHM rasters on the same pixel grid.

Two rasters are on the same pixel grid when they have the same CRS, the same north-up pixel
size, and origins that differ by a whole number of pixels (tolerance 1e-6 pixel). Their
extents may differ: the difference covers their intersection (default) or their union, with
nodata wherever either input has no value. Output: ``to - from``, float32, nodata
:data:`NODATA`, a Cloud-Optimized GeoTIFF written atomically by the one COG writer of the
project, :func:`standgrid.geotiff.write_cog` (GDAL ``COG`` driver; a tiled GeoTIFF
with overviews when that driver is missing), with its QGIS style beside it (``<name>.qml``).
Two rasters without CRS (local coordinates) count as the same CRS; square pixels are
required.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from standgrid.crs import CRS
from standgrid.errors import GridMismatchError
from standgrid.export.styles import write_raster_style
from standgrid.geotiff import NODATA, read_grid, read_window, write_cog
from standgrid.rastergrid import RasterGrid

ALIGNMENT_TOLERANCE_PX = 1e-6


@dataclass(frozen=True)
class ChmDifference:
    """What :func:`chm_difference` wrote."""

    path: Path
    width: int
    height: int
    transform: tuple[float, ...]  # affine a, b, c, d, e, f
    crs: CRS | None
    valid_pixels: int
    mean_change_m: float | None


def _check_same_pixel_grid(a: RasterGrid, b: RasterGrid, where: str) -> None:
    """Raise :class:`GridMismatchError` unless ``a`` and ``b`` share CRS, pixel size, alignment."""
    if a.crs != b.crs:
        raise GridMismatchError(f"different CRS: {a.crs} vs {b.crs} ({where})")
    if not np.isclose(a.pixel_size, b.pixel_size, rtol=1e-9, atol=0):
        raise GridMismatchError(
            f"different pixel size: {a.pixel_size} x {a.pixel_size} m vs "
            f"{b.pixel_size} x {b.pixel_size} m ({where})"
        )
    ta, tb = a.transform, b.transform
    for name, offset, size in (("x", tb.c - ta.c, ta.a), ("y", tb.f - ta.f, -ta.e)):
        pixels = offset / size
        if abs(pixels - round(pixels)) > ALIGNMENT_TOLERANCE_PX:
            raise GridMismatchError(
                f"pixel grids not aligned: {name} origins differ by {offset} m = {pixels:.6f} "
                f"pixels, not a whole number ({where})"
            )


def _read_into(path: Path, grid: RasterGrid, out: np.ndarray, target: RasterGrid) -> None:
    """Paste band 1 of the raster at ``path`` (its ``grid``; float64, NaN = nodata) into
    ``out``, an array of the aligned grid ``target``."""
    left, top = target.bounds[0], target.bounds[3]
    res = target.pixel_size
    col0 = round((grid.bounds[0] - left) / res)
    row0 = round((top - grid.bounds[3]) / res)
    # overlap in output pixel indices
    r_start, r_stop = max(row0, 0), min(row0 + grid.nrows, out.shape[0])
    c_start, c_stop = max(col0, 0), min(col0 + grid.ncols, out.shape[1])
    if r_start >= r_stop or c_start >= c_stop:
        return
    from rasterio.windows import Window

    window = Window(c_start - col0, r_start - row0, c_stop - c_start, r_stop - r_start)
    out[r_start:r_stop, c_start:c_stop] = read_window(path, window)


def read_aligned_pair(
    path_a: str | os.PathLike[str],
    path_b: str | os.PathLike[str],
    *,
    extent: Literal["intersection", "union"] = "intersection",
) -> tuple[np.ndarray, np.ndarray, RasterGrid]:
    """Band 1 of two rasters on the same pixel grid, read onto their common (intersection)
    or joint (union) extent: (a, b, grid), float64 with NaN for nodata and outside."""
    if extent not in ("intersection", "union"):
        raise ValueError(f"extent must be 'intersection' or 'union', not {extent!r}")
    path_a, path_b = Path(path_a), Path(path_b)
    a, b = read_grid(path_a), read_grid(path_b)
    _check_same_pixel_grid(a, b, f"{path_a} vs {path_b}")
    res = a.pixel_size
    pick = (max, min) if extent == "intersection" else (min, max)
    left, right = pick[0](a.bounds[0], b.bounds[0]), pick[1](a.bounds[2], b.bounds[2])
    bottom, top = pick[0](a.bounds[1], b.bounds[1]), pick[1](a.bounds[3], b.bounds[3])
    width = round((right - left) / res)
    height = round((top - bottom) / res)
    if width <= 0 or height <= 0:
        raise GridMismatchError(f"rasters do not overlap ({path_a} vs {path_b})")
    grid = RasterGrid(left, top - height * res, res, width, height, a.crs)
    first = np.full((height, width), np.nan)
    second = np.full((height, width), np.nan)
    _read_into(path_a, a, first, grid)
    _read_into(path_b, b, second, grid)
    return first, second, grid


def chm_difference(
    chm_from_path: str | os.PathLike[str],
    chm_to_path: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    *,
    extent: Literal["intersection", "union"] = "intersection",
    overwrite: bool = True,
    style: str | os.PathLike[str] | None = None,
) -> ChmDifference:
    """Write ``to - from`` of two CHMs on the same pixel grid (rules: module docstring).

    Its default QGIS style (diverging ramp centred on 0, +-p98 of the change, legend in m)
    goes beside it as ``<name>.qml``, or to ``style`` when given.
    """
    before, after, grid = read_aligned_pair(chm_from_path, chm_to_path, extent=extent)
    difference = after - before
    valid = np.isfinite(difference)
    data = np.where(valid, difference, NODATA).astype(np.float32)

    final = Path(out_path)
    write_cog(
        final,
        data,
        grid,
        nodata=NODATA,
        description="CHM difference to - from (m)",
        overwrite=overwrite,
    )
    write_raster_style(final, "chm_change", qml=style)  # diverging ramp around 0 for QGIS
    n_valid = int(valid.sum())
    return ChmDifference(
        path=final,
        width=grid.ncols,
        height=grid.nrows,
        transform=tuple(grid.transform)[:6],
        crs=grid.crs,
        valid_pixels=n_valid,
        mean_change_m=float(difference[valid].mean()) if n_valid else None,
    )
