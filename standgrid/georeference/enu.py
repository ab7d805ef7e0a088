"""Exact local East-North-Up frames on the WGS 84 ellipsoid.

Geodetic <-> ECEF goes through pyproj (EPSG:4979 <-> EPSG:4978, ``always_xy``, ``errcheck``;
the two Transformers are built once); ECEF <-> ENU is the exact rotation about the reference
point, so no approximation is made anywhere. Latitudes/longitudes are degrees, heights
ellipsoidal metres, everything float64 and vectorised.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pyproj import Transformer
from pyproj.exceptions import ProjError

from standgrid.crs import CRS
from standgrid.errors import GeoreferenceError

FloatArray = NDArray[np.float64]
LLA = tuple[float, float, float]

#: WGS 84 3-D geographic (lat, lon, ellipsoidal height) and geocentric (ECEF) CRSs.
GEOGRAPHIC_3D = "EPSG:4979"
GEOCENTRIC = "EPSG:4978"


def _lla_to_ecef_transformer() -> Transformer:
    return CRS.of(GEOGRAPHIC_3D).transformer_to(GEOCENTRIC)


def _ecef_to_lla_transformer() -> Transformer:
    return CRS.of(GEOCENTRIC).transformer_to(GEOGRAPHIC_3D)


def _f64(a: ArrayLike) -> FloatArray:
    return np.asarray(a, dtype=np.float64)


def lla_to_ecef(
    lat: ArrayLike, lon: ArrayLike, alt: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Geodetic (degrees, ellipsoidal m) -> ECEF ``(x, y, z)`` metres."""
    try:
        x, y, z = _lla_to_ecef_transformer().transform(
            _f64(lon), _f64(lat), _f64(alt), errcheck=True
        )
    except ProjError as exc:
        raise GeoreferenceError(
            f"geodetic -> ECEF failed (latitude outside +-90 deg?): {exc}"
        ) from exc
    return _f64(x), _f64(y), _f64(z)


def ecef_to_lla(
    x: ArrayLike, y: ArrayLike, z: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """ECEF metres -> geodetic ``(lat, lon, alt)`` (degrees, ellipsoidal m)."""
    try:
        lon, lat, alt = _ecef_to_lla_transformer().transform(
            _f64(x), _f64(y), _f64(z), errcheck=True
        )
    except ProjError as exc:
        raise GeoreferenceError(f"ECEF -> geodetic failed: {exc}") from exc
    return _f64(lat), _f64(lon), _f64(alt)


def enu_rotation(lat: float, lon: float) -> FloatArray:
    """``R_enu_ecef`` (3x3): rotates ECEF offsets into East-North-Up at ``lat``/``lon`` (degrees).

    Rows are the East, North and Up unit vectors in ECEF; ``R.T`` maps ENU back into ECEF.
    """
    phi, lam = np.radians(float(lat)), np.radians(float(lon))
    sp, cp, sl, cl = np.sin(phi), np.cos(phi), np.sin(lam), np.cos(lam)
    return np.array(
        [
            [-sl, cl, 0.0],
            [-sp * cl, -sp * sl, cp],
            [cp * cl, cp * sl, sp],
        ],
        dtype=np.float64,
    )


def reference_ecef(ref: LLA) -> FloatArray:
    """ECEF position ``(3,)`` of an ENU origin ``(lat, lon, alt)``."""
    x, y, z = lla_to_ecef(ref[0], ref[1], ref[2])
    return np.array([float(x), float(y), float(z)], dtype=np.float64)


def enu_to_ecef_points(enu: ArrayLike, ref: LLA) -> FloatArray:
    """ENU points ``(N, 3)`` around ``ref`` -> ECEF ``(N, 3)``."""
    pts = _f64(enu)
    return pts @ enu_rotation(ref[0], ref[1]) + reference_ecef(ref)


def ecef_to_enu_points(ecef: ArrayLike, ref: LLA) -> FloatArray:
    """ECEF points ``(N, 3)`` -> ENU ``(N, 3)`` around ``ref``."""
    pts = _f64(ecef)
    return (pts - reference_ecef(ref)) @ enu_rotation(ref[0], ref[1]).T


def lla_to_enu(
    lat: ArrayLike, lon: ArrayLike, alt: ArrayLike, ref: LLA
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Geodetic -> ``(e, n, u)`` metres in the ENU frame at ``ref = (lat, lon, alt)``."""
    x, y, z = lla_to_ecef(lat, lon, alt)
    shape = x.shape
    enu = ecef_to_enu_points(np.stack([x.ravel(), y.ravel(), z.ravel()], axis=-1), ref)
    return enu[:, 0].reshape(shape), enu[:, 1].reshape(shape), enu[:, 2].reshape(shape)


def enu_to_lla(
    e: ArrayLike, n: ArrayLike, u: ArrayLike, ref: LLA
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(e, n, u)`` metres in the ENU frame at ``ref`` -> geodetic ``(lat, lon, alt)``."""
    e_arr, n_arr, u_arr = np.broadcast_arrays(_f64(e), _f64(n), _f64(u))
    shape = e_arr.shape
    ecef = enu_to_ecef_points(np.stack([e_arr.ravel(), n_arr.ravel(), u_arr.ravel()], axis=-1), ref)
    lat, lon, alt = ecef_to_lla(ecef[:, 0], ecef[:, 1], ecef[:, 2])
    return lat.reshape(shape), lon.reshape(shape), alt.reshape(shape)
