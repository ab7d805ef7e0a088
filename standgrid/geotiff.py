"""Single-band GeoTIFFs: Cloud-Optimized writes and reads of a :class:`RasterGrid`.

Every raster standgrid writes (DTM, CHM, density, coverage, CHM change) goes through
:func:`write_cog` (GDAL's ``COG`` driver; a tiled GeoTIFF with overviews when it is missing),
atomically, in its grid's CRS; :func:`read_raster` / :func:`read_window` read them back.
"""

from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from standgrid._atomic import atomic_output
from standgrid.crs import CRS
from standgrid.errors import EnrichError, FormatError
from standgrid.rastergrid import RasterGrid

if TYPE_CHECKING:
    from rasterio.windows import Window

#: The no-data value of every raster standgrid writes (DTM, CHM, density, CHM change).
NODATA = -9999.0


def write_cog(
    path: str | os.PathLike[str],
    array: NDArray[np.generic],
    grid: RasterGrid,
    *,
    nodata: float | None = None,
    description: str | None = None,
    overwrite: bool = True,
    blocksize: int = 256,
) -> None:
    """Write one band as a Cloud-Optimized GeoTIFF (deflate, tiled, overviews), atomically.

    NaN pixels are written as ``nodata`` when given (NaN is the nodata of float rasters
    by default). The CRS is the grid's (none for local coordinates).
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
    if grid.crs is not None:
        profile["crs"] = rasterio.crs.CRS.from_user_input(grid.crs.text)
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
    """A single-band raster read back: values (NaN for nodata), its grid (with its CRS),
    description."""

    array: NDArray[np.float64]
    grid: RasterGrid
    description: str | None

    @property
    def crs(self) -> CRS | None:
        return self.grid.crs


def read_grid(path: str | os.PathLike[str]) -> RasterGrid:
    """The grid of a north-up raster with square pixels and at least one band."""
    import rasterio
    from rasterio.errors import RasterioIOError

    try:
        with rasterio.open(path) as ds:
            return _grid(ds, path)
    except RasterioIOError as exc:
        raise FormatError(f"cannot read raster: {exc}", path=path) from exc


def read_raster(path: str | os.PathLike[str]) -> RasterData:
    """Read a north-up single-band raster written by :func:`write_cog` (nodata -> NaN)."""
    import rasterio
    from rasterio.errors import RasterioIOError

    try:
        with rasterio.open(path) as ds:
            grid = _grid(ds, path)
            data = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
            description = ds.descriptions[0] if ds.descriptions else None
    except RasterioIOError as exc:
        raise FormatError(f"cannot read raster: {exc}", path=path) from exc
    return RasterData(data, grid, description)


def read_window(path: str | os.PathLike[str], window: Window) -> NDArray[np.float64]:
    """Band 1 of a raster inside ``window`` (of its own grid), float64 with NaN for nodata."""
    import rasterio
    from rasterio.errors import RasterioIOError

    try:
        with rasterio.open(path) as src:
            data = src.read(1, window=window, masked=True)
    except RasterioIOError as exc:
        raise FormatError(f"cannot read raster: {exc}", path=path) from exc
    return np.ma.filled(data.astype(np.float64), np.nan)


def _grid(ds: Any, path: str | os.PathLike[str]) -> RasterGrid:
    t = ds.transform
    if ds.count < 1:
        raise FormatError("raster has no band", path=path)
    if t.b != 0 or t.d != 0 or t.e != -t.a or t.a <= 0:
        raise FormatError("not a north-up raster with square pixels", path=path)
    crs = None if not ds.crs else CRS.of(ds.crs.to_wkt())
    return RasterGrid(t.c, t.f + t.e * ds.height, t.a, ds.width, ds.height, crs)
