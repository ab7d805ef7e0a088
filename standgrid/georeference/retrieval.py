"""Retrieve a mission's payloads by GNSS coordinate: LLA -> ENU -> map, then by pose."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from standgrid.geometry import invert_pose, transform_points
from standgrid.georeference.enu import lla_to_enu
from standgrid.georeference.mission import georeference_mission
from standgrid.mission.model import Mission, Payload, open_mission
from standgrid.mission.retrieval import retrieve_payload_by_pose


def retrieve_payload_by_gnss(
    mission_folder_path: str | Path | Mission,
    gnss: ArrayLike,
    **by_pose: Any,
) -> list[Payload]:
    """Payloads near a GNSS coordinate ``(lat, lon[, alt])`` (WGS84 degrees, metres).

    Needs a georeference: the mission is fitted with
    :func:`georeference_mission` (its graph's GNSS anchor, or a fit of its
    GNSS fixes) and the coordinate goes LLA -> ENU -> map before
    :func:`retrieve_payload_by_pose` (keyword arguments are passed on). Raises
    :class:`NotGeoreferencedError` (no GNSS and no anchor) or :class:`InsufficientGnssError`
    when no georeference can be made.
    """
    coord = np.asarray(gnss, dtype=np.float64).ravel()
    if coord.shape not in ((2,), (3,)):
        raise ValueError(f"gnss must be (lat, lon) or (lat, lon, alt), got {coord.tolist()}")
    mission = (
        mission_folder_path
        if isinstance(mission_folder_path, Mission)
        else open_mission(mission_folder_path, strict=False)
    )
    xyz_map = gnss_to_map(mission, coord)
    return retrieve_payload_by_pose(mission, xyz_map, **by_pose)


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
