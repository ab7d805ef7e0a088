"""Retrieve a mission's payloads by GNSS coordinate: LLA -> ENU -> map, then by pose."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from standgrid.errors import PayloadTooFarError
from standgrid.geometry import invert_pose, transform_points
from standgrid.georeference.enu import enu_to_lla, lla_to_enu
from standgrid.georeference.location import swap_hint
from standgrid.georeference.mission import georeference_mission
from standgrid.mission.model import Mission
from standgrid.mission.opening import open_mission
from standgrid.mission.payload import Payload
from standgrid.mission.retrieval import query_distances, retrieve_payload_by_pose

#: Metres: the default largest distance from a GNSS query to its nearest payload.
DEFAULT_MAX_DISTANCE_M = 1000.0


@dataclass(frozen=True)
class GnssMatch:
    """Payloads found near a GNSS coordinate (nearest first), the coordinate in the map
    frame (``query_map``) and each payload's distance to it (m, ``distances_m``)."""

    payloads: list[Payload]
    query_map: NDArray[np.float64]
    distances_m: list[float]


def retrieve_payload_by_gnss(
    mission_folder_path: str | Path | Mission,
    gnss: ArrayLike,
    *,
    max_distance: float | None = DEFAULT_MAX_DISTANCE_M,
    **by_pose: Any,
) -> list[Payload]:
    """Payloads near a GNSS coordinate ``(lat, lon[, alt])`` (WGS84 degrees, metres).

    Needs a georeference: the mission is fitted with
    :func:`georeference_mission` (its graph's GNSS anchor, or a fit of its
    GNSS fixes) and the coordinate goes LLA -> ENU -> map before
    :func:`retrieve_payload_by_pose` (keyword arguments are passed on). Raises
    :class:`NotGeoreferencedError` (no GNSS and no anchor) or :class:`InsufficientGnssError`
    when no georeference can be made, and :class:`PayloadTooFarError` when the nearest
    payload is more than ``max_distance`` metres away (None: no limit). Distances:
    :func:`locate_by_gnss`.
    """
    return locate_by_gnss(mission_folder_path, gnss, max_distance=max_distance, **by_pose).payloads


def locate_by_gnss(
    mission_folder_path: str | Path | Mission,
    gnss: ArrayLike,
    *,
    max_distance: float | None = DEFAULT_MAX_DISTANCE_M,
    **by_pose: Any,
) -> GnssMatch:
    """:func:`retrieve_payload_by_gnss` with the map-frame query and each payload's distance."""
    coord = np.asarray(gnss, dtype=np.float64).ravel()
    if coord.shape not in ((2,), (3,)):
        raise ValueError(f"gnss must be (lat, lon) or (lat, lon, alt), got {coord.tolist()}")
    mission = (
        mission_folder_path
        if isinstance(mission_folder_path, Mission)
        else open_mission(mission_folder_path, strict=False)
    )
    xyz_map = gnss_to_map(mission, coord)
    found = retrieve_payload_by_pose(mission, xyz_map, **by_pose)
    positions = np.array([mission.pose_of(p)[:3, 3] for p in found]).reshape(-1, 3)
    distances = query_distances(xyz_map, positions)
    nearest = float(distances.min())
    if max_distance is not None and nearest > max_distance:
        raise _too_far(mission, coord, found[int(np.argmin(distances))], max_distance)
    return GnssMatch(found, xyz_map, [float(d) for d in distances])


def _too_far(
    mission: Mission, coord: NDArray[np.float64], nearest: Payload, max_distance: float
) -> PayloadTooFarError:
    """The error for a GNSS query far from every payload: the geodesic distance (WGS 84) to
    the nearest one and, when latitude and longitude read the other way round land near a
    payload, that hint."""
    from pyproj import Geod

    fit = georeference_mission(mission)
    lat, lon = float(coord[0]), float(coord[1])
    enu = transform_points(fit.T_enu_map, mission.pose_of(nearest)[:3, 3].reshape(1, 3))[0]
    at_lat, at_lon, _ = enu_to_lla(enu[0], enu[1], enu[2], fit.lla_ref)
    _, _, metres = Geod(ellps="WGS84").inv(lon, lat, float(at_lon), float(at_lat))

    def nearest_payload_m(la: float, lo: float) -> float:
        there = gnss_to_map(mission, np.array([la, lo, *coord[2:]]))
        other = retrieve_payload_by_pose(mission, there, k=1)[0]
        return float(query_distances(there, mission.pose_of(other)[:3, 3].reshape(1, 3))[0])

    hint = swap_hint(
        lat,
        lon,
        nearest_payload_m,
        max_distance,
        what="the nearest payload is",
        advice="give LAT LON, latitude first",
    )
    hint = hint or "latitude comes first"
    return PayloadTooFarError(
        f"the payload nearest latitude {lat}, longitude {lon} is {metres / 1000:,.1f} km "
        f"away (at {float(at_lat):.5f}, {float(at_lon):.5f}), beyond the {max_distance:g} m "
        f"allowed; {hint}",
        path=mission.path,
    )


def gnss_to_map(mission: Mission, coord: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(lat, lon[, alt])`` -> map ``(x, y, z)`` through the mission's georeference fit.
    Without an altitude the height of the trajectory node nearest in x/y is used."""
    fit = georeference_mission(mission)
    lat, lon = coord[0], coord[1]
    alt = coord[2] if len(coord) == 3 else float(fit.lla_ref[2])
    e, n, u = lla_to_enu(np.array([lat]), np.array([lon]), np.array([alt]), fit.lla_ref)
    enu = np.array([[float(e[0]), float(n[0]), float(u[0])]])
    xyz = transform_points(invert_pose(fit.T_enu_map), enu)[0]
    if len(coord) == 2:
        _, positions = mission.trajectory()
        if len(positions):
            nearest = np.argmin(np.linalg.norm(positions[:, :2] - xyz[:2], axis=1))
            xyz[2] = positions[nearest, 2]
    return xyz
