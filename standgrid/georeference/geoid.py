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
"""

from __future__ import annotations

import json
import os
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


#: Best model first.
CANDIDATES = (
    _Candidate("EGM2008", 3858, ("us_nga_egm08_25.tif", "egm08_25.gtx")),
    _Candidate("EGM96", 10084, ("us_nga_egm96_15.tif", "egm96_15.gtx")),
)
#: The geoid undulation lies within about -107..+86 m everywhere: outside, the grid is wrong.
UNDULATION_RANGE_M = (-110.0, 90.0)


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
            np.asarray(lon, np.float64), np.asarray(lat, np.float64),
            np.asarray(height, np.float64),
        )  # fmt: skip
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
                        name=candidate.model, file=path,
                        operation=f"EPSG:{candidate.operation}",
                        vertical_crs=_id(target["target_crs"]),
                        accuracy_m=float(target.get("accuracy", "nan")),
                    )  # fmt: skip
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
    """None when PROJ opens ``path`` and gives an undulation in the world's range."""
    try:
        transformer = _transformer(candidate.operation, path)
        probes_lat, probes_lon = np.array([0.0, 45.0, -45.0]), np.array([0.0, 90.0, -90.0])
        _, _, out = transformer.transform(probes_lat, probes_lon, np.zeros(3))
    except ProjError as exc:
        return f"PROJ cannot use it ({exc})"
    undulation = -np.asarray(out, np.float64)
    low, high = UNDULATION_RANGE_M
    if not (np.all(np.isfinite(undulation)) and np.all((undulation > low) & (undulation < high))):
        return (
            f"undulations {undulation.tolist()} m at (0, 0), (90, 45), (-90, -45) are not a geoid's"
        )
    if np.all(undulation == 0.0):
        return "all undulations are 0: not a geoid grid"
    return None
