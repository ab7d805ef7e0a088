"""Is a mission where it says it is? Geodesic distances, and the latitude/longitude swap hint.

:func:`swap_hint` is the one place that says "read the other way round, it is near": both the
GNSS retrieval (``retrieve by-gnss``) and the placement check (:func:`check_location`) use it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from standgrid.errors import MisplacedMissionError

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from standgrid.georeference.fit import GeoreferenceFit

#: Metres: the farthest a fitted mission may lie from the location its metadata gives.
MAX_METADATA_DISTANCE_M = 10_000.0


def geodesic_m(
    lat: float, lon: float, lats: NDArray[np.float64], lons: NDArray[np.float64]
) -> NDArray[np.float64]:
    """WGS 84 geodesic distances (m) from ``(lat, lon)`` to each of ``(lats, lons)``."""
    from pyproj import Geod

    lats, lons = np.asarray(lats, dtype=np.float64), np.asarray(lons, dtype=np.float64)
    _, _, metres = Geod(ellps="WGS84").inv(
        np.full_like(lons, lon), np.full_like(lats, lat), lons, lats
    )
    return np.asarray(metres, dtype=np.float64)


def swap_hint(
    lat: float,
    lon: float,
    distance_at: Callable[[float, float], float],
    max_distance: float,
    *,
    what: str,
    advice: str,
) -> str | None:
    """``read as latitude <lon>, longitude <lat> (swapped) <what> <d> m away: <advice>`` when
    the coordinate read the other way round lies within ``max_distance`` metres of what it
    should be near (``distance_at(lat, lon)``, metres), else None."""
    if abs(lon) > 90.0:  # cannot be a latitude
        return None
    away = float(distance_at(lon, lat))
    if not away <= max_distance:
        return None
    return f"read as latitude {lon}, longitude {lat} (swapped) {what} {away:.1f} m away: {advice}"


def check_location(
    fit: GeoreferenceFit,
    positions_map: NDArray[np.float64],
    expected: tuple[float, float, float],
    *,
    source: Path | None,
    metadata: Path | None = None,
    max_distance: float = MAX_METADATA_DISTANCE_M,
) -> None:
    """Refuse (:class:`MisplacedMissionError`) a georeference that puts every trajectory node
    (``positions_map``, map frame) farther than ``max_distance`` metres from ``expected``
    (``(lat, lon, alt)``: the location ``metadata`` gives), with the swap hint when the fitted
    position read the other way round is near it."""
    from standgrid.georeference.enu import enu_to_lla

    points = np.asarray(positions_map, dtype=np.float64).reshape(-1, 3)
    if not len(points):
        points = np.zeros((1, 3))  # the map origin
    enu = fit.map_to_enu(points)
    lats, lons, _ = enu_to_lla(enu[:, 0], enu[:, 1], enu[:, 2], fit.lla_ref)
    lats, lons = np.atleast_1d(lats), np.atleast_1d(lons)
    want_lat, want_lon = float(expected[0]), float(expected[1])
    distances = geodesic_m(want_lat, want_lon, lats, lons)
    nearest = int(np.argmin(distances))
    if distances[nearest] <= max_distance:
        return
    lat, lon = round(float(lats[nearest]), 6), round(float(lons[nearest]), 6)

    def from_expected(la: float, lo: float) -> float:
        return float(geodesic_m(want_lat, want_lon, np.array([la]), np.array([lo]))[0])

    named = f" ({metadata})" if metadata is not None else ""
    hint = swap_hint(
        lat,
        lon,
        from_expected,
        max_distance,
        what="the mission would lie",
        advice="the GNSS log has latitude and longitude "
        "swapped (columns: sec, nsec, latitude, longitude, ...)",
    )
    raise MisplacedMissionError(
        f"the georeference ({fit.method}) puts the mission at latitude {lat}, longitude {lon}, "
        f"{distances[nearest] / 1000:,.1f} km from the location its metadata{named} gives "
        f"(latitude {want_lat:.6f}, longitude {want_lon:.6f}; at most {max_distance / 1000:g} "
        f"km allowed); "
        + (hint or "the GNSS fixes or the metadata are of another place")
        + " (accept it explicitly with option accept_poor_georeference)",
        path=source,
        option="accept_poor_georeference",
    )
