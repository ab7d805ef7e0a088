"""Geoid models: WGS 84 ellipsoidal heights -> orthometric heights (above "sea level").

standgrid's heights are WGS 84 ellipsoidal; users such as FVS want height above the geoid.
The geoid grids are not in pyproj's wheel (and the network is off), so :func:`find_geoid`
looks for a grid file PROJ reads (EGM2008 2.5', else EGM96 15') in a list of folders and
builds the EPSG transformation for it with the grid's absolute path: EPSG's own
operation (``WGS 84 to EGM2008 height (1)``, EPSG:3858, or ``WGS 84 to EGM96 height (1)``,
EPSG:10084, read from pyproj's proj.db as PROJJSON) with its "geoid model file" parameter
set to the file found. So the result comes from that grid or from nothing: PROJ cannot fall
back to its ballpark (no-op) vertical transformation, and pyproj's global search paths are
left alone (adding a folder to them would change the grids other transforms pick).
A grid is used only whole and sound: its file size matches its header (GTX), GDAL reads
every value, each finite and a plausible undulation, no row filled with one value, the node
spacing is the model's, and PROJ gives the known undulation at :data:`ANCHORS` (which
catches a sign flip); each file is checked once per process and version.
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import pyproj
from numpy.typing import ArrayLike, NDArray
from pyproj.crs import CoordinateOperation
from pyproj.exceptions import ProjError

#: Folders searched (os.pathsep-separated) instead of the defaults, when set.
SEARCH_PATH_ENV = "STANDGRID_GEOID_PATH"
#: Debian/Ubuntu ``proj-data`` package.
DEBIAN_PROJ_DATA = Path("/usr/share/proj")


@dataclass(frozen=True)
class _Candidate:
    model: str
    operation: int  # EPSG code of the WGS 84 -> gravity-related height transformation
    files: tuple[str, ...]  # PROJ-data name, then the older PROJ (Debian proj-data) name
    spacing_deg: float  # the grid's node spacing


#: Best model first.
CANDIDATES = (
    _Candidate("EGM2008", 3858, ("us_nga_egm08_25.tif", "egm08_25.gtx"), 2.5 / 60),
    _Candidate("EGM96", 10084, ("us_nga_egm96_15.tif", "egm96_15.gtx"), 15 / 60),
)
#: The geoid undulation lies within about -107..+86 m everywhere: outside, the grid is wrong.
UNDULATION_RANGE_M = (-110.0, 90.0)
#: lon, lat, N (m): EGM96's undulation at the equator/prime meridian, both poles and the
#: bundled Wytham Woods missions; EGM2008's agree within about 1 m.
ANCHORS = ((0.0, 0.0, 17.16), (0.0, 90.0, 13.61), (0.0, -90.0, -29.53), (-1.337, 51.773, 47.89))
#: How far (m) a grid's undulation at an :data:`ANCHORS` point may be from the anchor's.
ANCHOR_TOLERANCE_M = 2.0
#: A grid row (but the poles') whose neighbouring values are equal this often is a fill.
CONSTANT_ROW_FRACTION = 0.5
#: Rows read at a time when checking a grid (EGM2008 2.5': 8640 columns, 35 MB per 1000).
_CHECK_ROWS = 1024
#: (path, size, mtime) -> the check's verdict: each grid file is read once per process.
_VERDICTS: dict[tuple[str, int, int], str | None] = {}


@dataclass(frozen=True)
class GeoidModel:
    """A geoid grid PROJ reads, and the EPSG transformation that applies it."""

    name: str  # "EGM96"
    file: Path
    operation: str  # "EPSG:10084"
    vertical_crs: str  # "EPSG:5773" (EGM96 height)
    accuracy_m: float  # the EPSG operation's stated accuracy

    @cached_property
    def _transformer(self) -> pyproj.Transformer:
        return _transformer(int(self.operation.split(":")[1]), self.file)

    def undulation(self, lon: ArrayLike, lat: ArrayLike) -> NDArray[np.float64]:
        """Geoid height N (m above the WGS 84 ellipsoid) at ``lon``/``lat`` (degrees);
        NaN where the grid has no value."""
        lon_, lat_ = np.broadcast_arrays(np.asarray(lon, np.float64), np.asarray(lat, np.float64))
        return -self.orthometric_height(lon_, lat_, np.zeros(lon_.shape))

    def orthometric_height(
        self, lon: ArrayLike, lat: ArrayLike, height: ArrayLike
    ) -> NDArray[np.float64]:
        """``height`` (m, WGS 84 ellipsoidal) at ``lon``/``lat`` (degrees) as height above
        the geoid H = h - N (m); NaN where the grid has no value."""
        lon_, lat_, h = np.broadcast_arrays(
            np.asarray(lon, np.float64),
            np.asarray(lat, np.float64),
            np.asarray(height, np.float64),
        )
        # the EPSG operation's source is EPSG:4979, latitude first (its pipeline swaps)
        _, _, out = self._transformer.transform(lat_.ravel(), lon_.ravel(), h.ravel())
        result = np.asarray(out, np.float64).reshape(h.shape)
        result[~np.isfinite(result)] = np.nan  # PROJ: inf outside the grid
        return result

    def describe(self) -> str:
        """One line for reports: model, vertical CRS, operation, accuracy and file."""
        return (
            f"{self.name} height ({self.vertical_crs}) through {self.operation} "
            f"(accuracy {self.accuracy_m:g} m) with the grid {self.file}"
        )


@dataclass(frozen=True)
class NoGeoidModel:
    """No usable geoid grid: where it was looked for, and what was wrong with files found."""

    searched: tuple[Path, ...]
    problems: tuple[str, ...] = ()

    @property
    def reason(self) -> str:
        names = ", ".join(f for c in CANDIDATES for f in c.files)
        text = (
            f"no geoid model found (looked for {names} in: "
            f"{', '.join(str(p) for p in self.searched) or 'no folder'})"
        )
        return text + "".join(f"; {p}" for p in self.problems)


def default_search_dirs() -> tuple[Path, ...]:
    """``$STANDGRID_GEOID_PATH`` when set; else ``$PROJ_DATA``, ``$PROJ_LIB``, pyproj's
    data folder, pyproj's user data folder and Debian's ``/usr/share/proj``."""
    override = os.environ.get(SEARCH_PATH_ENV)
    if override is not None:
        return _split(override)
    entries = [os.environ.get("PROJ_DATA", ""), os.environ.get("PROJ_LIB", "")]
    entries += [pyproj.datadir.get_data_dir(), pyproj.datadir.get_user_data_dir()]
    return _split(os.pathsep.join([*entries, str(DEBIAN_PROJ_DATA)]))


def _split(text: str) -> tuple[Path, ...]:
    dirs = [Path(p) for p in text.split(os.pathsep) if p]
    return tuple(dict.fromkeys(dirs))


def find_geoid(search_dirs: Sequence[str | Path] | None = None) -> GeoidModel | NoGeoidModel:
    """The best geoid grid in ``search_dirs`` (default :func:`default_search_dirs`), checked
    to work, or :class:`NoGeoidModel` saying where it looked."""
    dirs = default_search_dirs() if search_dirs is None else tuple(Path(d) for d in search_dirs)
    problems: list[str] = []
    for candidate in CANDIDATES:
        for folder in dirs:
            for name in candidate.files:
                path = (folder / name).absolute()
                if not path.is_file():
                    continue
                problem = _check(candidate, path)
                if problem is None:
                    target = CoordinateOperation.from_epsg(candidate.operation).to_json_dict()
                    return GeoidModel(
                        name=candidate.model,
                        file=path,
                        operation=f"EPSG:{candidate.operation}",
                        vertical_crs=_id(target["target_crs"]),
                        accuracy_m=float(target.get("accuracy", "nan")),
                    )
                problems.append(f"{path}: {problem}")
    return NoGeoidModel(dirs, tuple(problems))


def _id(crs: dict) -> str:
    ident = crs.get("id", {})
    return f"{ident['authority']}:{ident['code']}" if ident else str(crs.get("name"))


def _transformer(operation: int, grid: Path) -> pyproj.Transformer:
    definition = CoordinateOperation.from_epsg(operation).to_json_dict()
    (param,) = [p for p in definition["parameters"] if "model file" in p["name"]]
    param["value"] = str(grid)
    transformer = pyproj.Transformer.from_pipeline(json.dumps(definition))
    if f"grids={grid}" not in transformer.definition:  # the grid, and nothing else, applies
        raise ProjError(f"PROJ did not apply {grid}: {transformer.definition}")
    return transformer


def _check(candidate: _Candidate, path: Path) -> str | None:
    """None when ``path`` is a whole, sound geoid grid that PROJ applies with the right sign;
    else what is wrong. The verdict is cached per (path, size, mtime)."""
    stat = path.stat()
    key = (str(path), stat.st_size, stat.st_mtime_ns)
    if key not in _VERDICTS:
        _VERDICTS[key] = _grid_problem(candidate, path, stat.st_size) or _anchor_problem(
            candidate, path
        )
    return _VERDICTS[key]


def _gtx_problem(path: Path, size: int) -> str | None:
    """None when the GTX header's rows x columns of float32 fill the file exactly."""
    with open(path, "rb") as f:
        header = f.read(40)
    if len(header) < 40:
        return f"{size} bytes: shorter than a GTX header (40 bytes)"
    *_, rows, cols = struct.unpack(">4d2i", header)
    expected = 40 + 4 * rows * cols
    if rows <= 0 or cols <= 0 or size != expected:
        return (
            f"{size} bytes, but its GTX header says {rows} x {cols} values "
            f"({expected} bytes): truncated or damaged"
        )
    return None


def _grid_problem(candidate: _Candidate, path: Path, size: int) -> str | None:
    """None when the whole grid reads (GDAL), at the candidate's spacing, every value finite
    and in :data:`UNDULATION_RANGE_M`, no row but the poles' a constant fill."""
    import rasterio
    from rasterio.windows import Window

    if path.suffix.lower() == ".gtx" and (problem := _gtx_problem(path, size)) is not None:
        return problem
    low, high = UNDULATION_RANGE_M
    try:
        with rasterio.open(path) as src:
            spacing = (abs(src.transform.a), abs(src.transform.e))
            if not np.allclose(spacing, candidate.spacing_deg, rtol=1e-6):
                return (
                    f"node spacing {spacing[0]:g} x {spacing[1]:g} deg, not {candidate.model}'s "
                    f"{candidate.spacing_deg:g} deg"
                )
            nodata = src.nodata
            for top in range(0, src.height, _CHECK_ROWS):
                rows = min(_CHECK_ROWS, src.height - top)
                values = src.read(1, window=Window(0, top, src.width, rows)).astype(np.float64)
                if nodata is not None:
                    values[values == nodata] = np.nan
                bad = ~(np.isfinite(values) & (values >= low) & (values <= high))
                if bad.any():
                    row, col = (int(i) for i in np.argwhere(bad)[0])
                    return (
                        f"value {values[row, col]} at row {top + row}, column {col}: "
                        f"not a geoid undulation ({low:g}..{high:g} m)"
                    )
                same = (np.diff(values, axis=1) == 0).mean(axis=1) > CONSTANT_ROW_FRACTION
                same &= ~np.isin(np.arange(top, top + rows), (0, src.height - 1))  # poles
                if same.any():
                    first = int(np.argmax(same))
                    return (
                        f"row {top + first} is a constant fill "
                        f"({values[first, 0]:g} m): not a geoid grid"
                    )
    except rasterio.errors.RasterioError as exc:
        return f"GDAL cannot read it whole ({exc})"
    return None


def _anchor_problem(candidate: _Candidate, path: Path) -> str | None:
    """None when PROJ, through the grid, gives the :data:`ANCHORS` undulations within
    :data:`ANCHOR_TOLERANCE_M` (which catches a flipped sign or a scaled grid)."""
    lon, lat, expected = (np.array(v) for v in zip(*ANCHORS, strict=True))
    try:
        transformer = _transformer(candidate.operation, path)
        _, _, out = transformer.transform(lat, lon, np.zeros(len(lat)))
    except ProjError as exc:
        return f"PROJ cannot use it ({exc})"
    undulation = -np.asarray(out, np.float64)
    off = ~(np.abs(undulation - expected) <= ANCHOR_TOLERANCE_M)
    if off.any():
        where = ", ".join(
            f"N({x:g}, {y:g}) = {n:.2f} m, not {e:g}"
            for x, y, n, e in zip(lon[off], lat[off], undulation[off], expected[off], strict=True)
        )
        return f"through PROJ {where} (+-{ANCHOR_TOLERANCE_M:g} m): not {candidate.model}"
    return None
