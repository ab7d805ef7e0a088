"""Canopy height change: the difference of two CHM rasters on the same pixel grid.

Two rasters are on the same pixel grid when they have the same CRS, the same north-up pixel
size, and origins that differ by a whole number of pixels (tolerance 1e-6 pixel). Their
extents may differ: the difference covers their intersection (default) or their union, with
nodata wherever either input has no value. Output: ``to - from``, float32, nodata
:data:`NODATA`, a Cloud-Optimized GeoTIFF written atomically by the one COG writer of the
project, :func:`standgrid.enrich.rasters.write_cog` (GDAL ``COG`` driver; a tiled GeoTIFF
with overviews when that driver is missing), with its QGIS style beside it (``<name>.qml``).
Two rasters without CRS (local coordinates) count as the same CRS; square pixels are
required.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from standgrid.enrich.rasters import NODATA, RasterGrid, raster_crs_text
from standgrid.errors import FormatError, GridMismatchError
from standgrid.export.styles import write_raster_style

ALIGNMENT_TOLERANCE_PX = 1e-6


@dataclass(frozen=True)
class ChmDifference:
    """What :func:`chm_difference` wrote."""

    path: Path
    width: int
    height: int
    transform: tuple[float, ...]  # affine a, b, c, d, e, f
    crs: str | None
    valid_pixels: int
    mean_change_m: float | None


@dataclass(frozen=True)
class _Grid:
    path: Path
    crs: Any
    transform: Any
    width: int
    height: int

    @property
    def left(self) -> float:
        return float(self.transform.c)

    @property
    def top(self) -> float:
        return float(self.transform.f)

    @property
    def right(self) -> float:
        return self.left + self.width * float(self.transform.a)

    @property
    def bottom(self) -> float:
        return self.top + self.height * float(self.transform.e)


def _open_grid(path: Path) -> _Grid:
    import rasterio

    try:
        with rasterio.open(path) as src:
            grid = _Grid(path, src.crs, src.transform, src.width, src.height)
            count = src.count
    except rasterio.errors.RasterioIOError as exc:
        raise FormatError(f"cannot read raster: {exc}", path=path) from exc
    if count < 1:
        raise FormatError("raster has no band", path=path)
    t = grid.transform
    if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
        raise FormatError("raster is not north-up (rotated or flipped transform)", path=path)
    return grid


def _check_same_pixel_grid(a: _Grid, b: _Grid) -> None:
    """Raise :class:`GridMismatchError` unless ``a`` and ``b`` share CRS, pixel size, alignment."""
    where = f"{a.path} vs {b.path}"
    if bool(a.crs) != bool(b.crs) or (a.crs and a.crs != b.crs):
        raise GridMismatchError(
            f"different CRS: {raster_crs_text(a.crs)} vs {raster_crs_text(b.crs)} ({where})"
        )
    ta, tb = a.transform, b.transform
    same_size = np.isclose(ta.a, tb.a, rtol=1e-9, atol=0) and np.isclose(
        ta.e, tb.e, rtol=1e-9, atol=0
    )
    if not same_size:
        raise GridMismatchError(
            f"different pixel size: {ta.a} x {-ta.e} m vs {tb.a} x {-tb.e} m ({where})"
        )
    for name, offset, size in (("x", tb.c - ta.c, ta.a), ("y", tb.f - ta.f, -ta.e)):
        pixels = offset / size
        if abs(pixels - round(pixels)) > ALIGNMENT_TOLERANCE_PX:
            raise GridMismatchError(
                f"pixel grids not aligned: {name} origins differ by {offset} m = {pixels:.6f} "
                f"pixels, not a whole number ({where})"
            )


def _read_into(
    grid: _Grid, out: np.ndarray, left: float, top: float, res: tuple[float, float]
) -> None:
    """Paste band 1 of ``grid`` (float64, NaN = nodata) into ``out`` whose corner is left/top."""
    import rasterio
    from rasterio.windows import Window

    col0 = round((grid.left - left) / res[0])
    row0 = round((top - grid.top) / res[1])
    # overlap in output pixel indices
    r_start, r_stop = max(row0, 0), min(row0 + grid.height, out.shape[0])
    c_start, c_stop = max(col0, 0), min(col0 + grid.width, out.shape[1])
    if r_start >= r_stop or c_start >= c_stop:
        return
    window = Window(c_start - col0, r_start - row0, c_stop - c_start, r_stop - r_start)
    try:
        with rasterio.open(grid.path) as src:
            data = src.read(1, window=window, masked=True)
    except rasterio.errors.RasterioIOError as exc:
        raise FormatError(f"cannot read raster: {exc}", path=grid.path) from exc
    values = np.ma.filled(data.astype(np.float64), np.nan)
    out[r_start:r_stop, c_start:c_stop] = values


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
    a = _open_grid(Path(path_a))
    b = _open_grid(Path(path_b))
    _check_same_pixel_grid(a, b)
    res = (float(a.transform.a), float(-a.transform.e))
    if not np.isclose(res[0], res[1], rtol=1e-9, atol=0):
        raise FormatError(f"non-square pixels {res[0]} x {res[1]} m", path=a.path)
    pick = (max, min) if extent == "intersection" else (min, max)
    left, right = pick[0](a.left, b.left), pick[1](a.right, b.right)
    bottom, top = pick[0](a.bottom, b.bottom), pick[1](a.top, b.top)
    width = round((right - left) / res[0])
    height = round((top - bottom) / res[1])
    if width <= 0 or height <= 0:
        raise GridMismatchError(f"rasters do not overlap ({a.path} vs {b.path})")
    first = np.full((height, width), np.nan)
    second = np.full((height, width), np.nan)
    _read_into(a, first, left, top, res)
    _read_into(b, second, left, top, res)
    grid = RasterGrid(left, top - height * res[0], res[0], width, height)
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
    crs_text = raster_crs_text(_open_grid(Path(chm_from_path)).crs)
    difference = after - before
    valid = np.isfinite(difference)
    data = np.where(valid, difference, NODATA).astype(np.float32)

    from standgrid.enrich.rasters import write_cog

    final = Path(out_path)
    write_cog(
        final,
        data,
        grid,
        crs=crs_text,
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
        crs=crs_text,
        valid_pixels=n_valid,
        mean_change_m=float(difference[valid].mean()) if n_valid else None,
    )
