"""Output coordinate reference systems: resolve a user's spec, store it canonically.

standgrid projects maps into *projected* (metric, x/y) CRSs only, and keeps a CRS as
``EPSG:XXXX`` or WKT2 text, never as a PROJ string. Heights are WGS 84 ellipsoidal heights,
so compound CRSs (with a vertical datum) are refused rather than silently mislabelled.
"""

from __future__ import annotations

import math

import pyproj
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info
from pyproj.exceptions import CRSError as PyprojCRSError

from standgrid.errors import CRSError

CRSSpec = int | str | pyproj.CRS

#: UTM covers these latitudes; beyond them a polar stereographic (UPS) CRS is needed.
UTM_LAT_RANGE = (-80.0, 84.0)


def resolve_crs(spec: CRSSpec, *, lon: float | None = None, lat: float | None = None) -> pyproj.CRS:
    """A projected :class:`pyproj.CRS` from ``spec``.

    ``spec`` is an EPSG code (``32630``), ``"EPSG:32630"``, WKT/WKT2 text, a ``pyproj.CRS``,
    or ``"auto"``: the WGS 84 UTM zone (EPSG:326xx north / 327xx south) of ``lon``/``lat``
    (degrees). Raises :class:`~standgrid.errors.CRSError` for unknown codes, PROJ strings,
    geographic/geocentric CRSs and compound (vertical-datum) CRSs.
    """
    if isinstance(spec, pyproj.CRS):
        crs = spec
    elif isinstance(spec, bool):  # bool is an int subclass: True is not EPSG:1
        raise CRSError(f"not a CRS: {spec!r}")
    elif isinstance(spec, int):
        try:
            crs = pyproj.CRS.from_epsg(spec)
        except PyprojCRSError as exc:
            raise CRSError(f"unknown EPSG code {spec}") from exc
    elif isinstance(spec, str):
        text = spec.strip()
        if text.lower() == "auto":
            return utm_crs_for(lon, lat)
        if text.startswith("+") or "+proj=" in text or text.lower().startswith("proj="):
            raise CRSError(
                f"PROJ strings are not accepted ({text[:40]!r}): give an EPSG code "
                "('EPSG:32630') or WKT2 text, which keep the datum unambiguous"
            )
        if not text:
            raise CRSError("empty CRS spec")
        try:
            crs = pyproj.CRS.from_user_input(text)
        except PyprojCRSError as exc:
            raise CRSError(f"unknown CRS {text[:80]!r}") from exc
    else:
        raise CRSError(f"not a CRS spec: {type(spec).__name__} {spec!r}")
    _require_projected(crs)
    return crs


def _require_projected(crs: pyproj.CRS) -> None:
    if crs.is_compound:
        raise CRSError(
            f"compound CRS {crs.name!r} refused: standgrid writes WGS 84 ellipsoidal heights, "
            "so give the horizontal projected CRS alone (e.g. its EPSG code)"
        )
    if not crs.is_projected:
        kind = (
            "geographic"
            if crs.is_geographic
            else "geocentric"
            if crs.is_geocentric
            else "non-projected"
        )
        raise CRSError(
            f"{kind} CRS {crs.name!r} refused: give a projected (metric x/y) CRS, "
            "e.g. 'auto' for UTM"
        )


def standard_utm_zone(lon: float, lat: float) -> int:
    """The UTM zone number of a point, with the Norway (32V) and Svalbard (31X-37X) exceptions.

    Latitude bands of the exceptions follow the MGRS grid zones 32V (56-64 N) and X (72-84 N).
    """
    zone = math.floor((lon + 180.0) / 6.0) % 60 + 1
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        zone = 32
    elif 72.0 <= lat <= 84.0 and 0.0 <= lon < 42.0:
        zone = 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37
    return zone


def utm_crs_for(lon: float | None, lat: float | None) -> pyproj.CRS:
    """The WGS 84 UTM CRS (EPSG:326xx / 327xx) containing ``lon``/``lat`` (degrees)."""
    if lon is None or lat is None or not (math.isfinite(lon) and math.isfinite(lat)):
        raise CRSError(f"'auto' CRS needs a finite lon/lat (got lon={lon}, lat={lat})")
    if not UTM_LAT_RANGE[0] <= lat <= UTM_LAT_RANGE[1] or not -180.0 <= lon <= 180.0:
        raise CRSError(
            f"'auto' CRS: lon={lon}, lat={lat} is outside UTM coverage; give a CRS explicitly"
        )
    infos = query_utm_crs_info(
        datum_name="WGS 84", area_of_interest=AreaOfInterest(lon, lat, lon, lat)
    )
    codes = [int(info.code) for info in infos if info.auth_name == "EPSG"]
    zone = standard_utm_zone(lon, lat)
    expected = (32600 if lat >= 0.0 else 32700) + zone
    regular = math.floor((lon + 180.0) / 6.0) % 60 + 1
    # The EPSG areas of use ignore the Norway/Svalbard exceptions, which national grids follow.
    if expected in codes or (codes and zone != regular):
        code = expected
    elif codes:
        code = codes[0]
    else:  # pragma: no cover - the PROJ database covers every zone
        raise CRSError(f"no WGS 84 UTM zone found for lon={lon}, lat={lat}")
    return pyproj.CRS.from_epsg(code)


def crs_to_text(crs: pyproj.CRS) -> str:
    """Canonical text: ``EPSG:XXXX`` when that code round-trips to an equal CRS, else WKT2_2019."""
    epsg = crs.to_epsg()
    if epsg is not None:
        try:
            if pyproj.CRS.from_epsg(epsg) == crs:
                return f"EPSG:{epsg}"
        except PyprojCRSError:  # pragma: no cover - to_epsg only returns known codes
            pass
    wkt = crs.to_wkt("WKT2_2019")
    if not wkt:
        raise CRSError(f"CRS {crs.name!r} cannot be written as WKT2")
    return wkt
