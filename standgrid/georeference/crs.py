"""Output coordinate reference systems: a user's spec (or ``"auto"``) as a projected CRS value.

standgrid projects maps into *projected* (metric, x/y) CRSs only (a
:class:`~standgrid.crs.CRS`, written as ``EPSG:XXXX`` or WKT2 text, never as a PROJ string).
Heights are WGS 84 ellipsoidal heights, so compound CRSs (with a vertical datum) are refused
rather than silently mislabelled.
"""

from __future__ import annotations

import math

from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

from standgrid.crs import CRS, CRSLike
from standgrid.errors import CRSError

#: UTM covers these latitudes; beyond them a polar stereographic (UPS) CRS is needed.
UTM_LAT_RANGE = (-80.0, 84.0)


def resolve_crs(spec: CRSLike, *, lon: float | None = None, lat: float | None = None) -> CRS:
    """The projected :class:`~standgrid.crs.CRS` ``spec`` names.

    ``spec`` is what :meth:`CRS.of <standgrid.crs.CRS.of>` takes, or ``"auto"``: the WGS 84
    UTM zone (EPSG:326xx north / 327xx south) of ``lon``/``lat`` (degrees). Raises
    :class:`~standgrid.errors.CRSError` for unknown codes, PROJ strings, geographic/geocentric
    CRSs and compound (vertical-datum) CRSs.
    """
    if isinstance(spec, str) and spec.strip().lower() == "auto":
        return utm_crs_for(lon, lat)
    return CRS.of(spec).projected()


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


def utm_crs_for(lon: float | None, lat: float | None) -> CRS:
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
    return CRS.of(code)
