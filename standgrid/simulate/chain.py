"""The exact frame chain of a simulated world: CRS -> geodetic -> ECEF -> ENU -> map.

``p_crs (x, y, h)`` --pyproj--> ``(lon, lat, h)`` on WGS 84 (EPSG:4979) --pyproj--> ECEF
(EPSG:4978) --rotation about the reference--> local ENU --``T_map_enu``--> SLAM map frame.
Heights are ellipsoidal and pass through the projected CRS unchanged. Every truth the
simulator writes is defined through this chain, so it round-trips to floating-point noise.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from standgrid.crs import CRS, CRSLike
from standgrid.geometry import Matrix4, invert_pose, transform_points

GEODETIC_3D = "EPSG:4979"
ECEF = "EPSG:4978"


def enu_rotation(lat_deg: float, lon_deg: float) -> NDArray[np.float64]:
    """``R_enu_ecef``: rows are the east, north and up unit vectors at (lat, lon)."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    sl, cl, sp, cp = np.sin(lon), np.cos(lon), np.sin(lat), np.cos(lat)
    return np.array(
        [[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]], dtype=np.float64
    )


class FrameChain:
    """Exact transforms between a CRS, WGS 84 geodetic, ECEF, ENU (about ``lla_ref``), map."""

    def __init__(
        self,
        crs: CRSLike,
        lla_ref: Sequence[float],
        T_map_enu: ArrayLike,
    ) -> None:
        self.crs = CRS.of(crs)
        self.lla_ref = (float(lla_ref[0]), float(lla_ref[1]), float(lla_ref[2]))
        self.T_map_enu: Matrix4 = np.asarray(T_map_enu, dtype=np.float64)
        self.T_enu_map: Matrix4 = invert_pose(self.T_map_enu)
        self._crs_to_geo = self.crs.transformer_to(GEODETIC_3D)
        self._geo_to_ecef = CRS.of(GEODETIC_3D).transformer_to(ECEF)
        lat, lon, alt = self.lla_ref
        self._R = enu_rotation(lat, lon)
        ex, ey, ez = self._geo_to_ecef.transform(lon, lat, alt)
        self._ecef_ref = np.array([ex, ey, ez], dtype=np.float64)

    @property
    def description(self) -> str:
        """The pyproj operation used for CRS -> geodetic (to reproduce the chain elsewhere)."""
        return str(self._crs_to_geo.description)

    # --- CRS <-> geodetic -----------------------------------------------------------------
    def crs_to_lla(self, xyz: ArrayLike) -> NDArray[np.float64]:
        """CRS ``(N, 3)`` -> ``(N, 3)`` columns lat, lon (degrees), ellipsoidal height."""
        p = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
        lon, lat, h = self._crs_to_geo.transform(p[:, 0], p[:, 1], p[:, 2])
        return np.column_stack([lat, lon, h])

    def lla_to_crs(self, lla: ArrayLike) -> NDArray[np.float64]:
        g = np.atleast_2d(np.asarray(lla, dtype=np.float64))
        x, y, z = self._crs_to_geo.transform(g[:, 1], g[:, 0], g[:, 2], direction="INVERSE")
        return np.column_stack([x, y, z])

    # --- geodetic <-> ENU -----------------------------------------------------------------
    def lla_to_enu(self, lla: ArrayLike) -> NDArray[np.float64]:
        g = np.atleast_2d(np.asarray(lla, dtype=np.float64))
        x, y, z = self._geo_to_ecef.transform(g[:, 1], g[:, 0], g[:, 2])
        ecef = np.column_stack([x, y, z])
        return (ecef - self._ecef_ref) @ self._R.T

    def enu_to_lla(self, enu: ArrayLike) -> NDArray[np.float64]:
        e = np.atleast_2d(np.asarray(enu, dtype=np.float64))
        ecef = e @ self._R + self._ecef_ref
        lon, lat, h = self._geo_to_ecef.transform(
            ecef[:, 0], ecef[:, 1], ecef[:, 2], direction="INVERSE"
        )
        return np.column_stack([lat, lon, h])

    # --- whole chain ----------------------------------------------------------------------
    def crs_to_map(self, xyz: ArrayLike) -> NDArray[np.float64]:
        """CRS ``(N, 3)`` -> map frame ``(N, 3)``."""
        return transform_points(self.T_map_enu, self.lla_to_enu(self.crs_to_lla(xyz)))

    def map_to_crs(self, xyz_map: ArrayLike) -> NDArray[np.float64]:
        """Map frame ``(N, 3)`` -> CRS ``(N, 3)``."""
        enu = transform_points(self.T_enu_map, np.atleast_2d(np.asarray(xyz_map, np.float64)))
        return self.lla_to_crs(self.enu_to_lla(enu))

    def map_to_lla(self, xyz_map: ArrayLike) -> NDArray[np.float64]:
        enu = transform_points(self.T_enu_map, np.atleast_2d(np.asarray(xyz_map, np.float64)))
        return self.enu_to_lla(enu)
