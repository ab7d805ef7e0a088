"""Project map-frame points into a projected CRS, exactly or per chunk by a verified affine.

The exact chain is map -> ENU (``fit.T_enu_map``) -> ECEF (the exact ENU rotation about the
reference point) -> target CRS (one pyproj Transformer from EPSG:4978, built once, always_xy,
errcheck). Output z is the **WGS 84 ellipsoidal height** in metres: target CRSs are 2-D
projected CRSs (compound CRSs are refused by :func:`resolve_crs`) and pyproj carries the
ellipsoidal height of the geocentric -> geographic step through unchanged. For a target on
another datum (NAD83, ETRS89, ...) x/y include whatever datum transformation PROJ selects
(often a null or Helmert shift without grids); ``to_map`` uses the same operation in
reverse, so the round trip is exact either way.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pyproj.enums import TransformDirection
from pyproj.exceptions import ProjError

from standgrid.crs import CRS, CRSLike
from standgrid.errors import GeoreferenceError

from .crs import resolve_crs
from .enu import GEOCENTRIC, ecef_to_lla, enu_rotation, reference_ecef
from .fit import GeoreferenceFit

FloatArray = NDArray[np.float64]

#: ``fast`` falls back to ``exact`` when the affine deviates more than this at a check point.
FAST_TOLERANCE_M = 0.5e-3
#: Chunks smaller than this go straight to ``exact`` (linearising costs ~27 exact points).
_FAST_MIN_POINTS = 64
#: Rows projected per block by :meth:`MapProjector.fast`.
_FAST_BLOCK_ROWS = 8192


def _as_points(xyz: ArrayLike) -> FloatArray:
    pts = np.asarray(xyz, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GeoreferenceError(f"expected points of shape (N, 3), got {pts.shape}")
    return pts


class MapProjector:
    """Map-frame points of one georeferenced mission -> a projected CRS (and back)."""

    def __init__(self, fit: GeoreferenceFit, crs: CRSLike) -> None:
        lat, lon, _ = fit.lla_ref
        self.fit = fit
        self.crs = resolve_crs(crs, lon=lon, lat=lat)
        r_enu_ecef = enu_rotation(lat, lon)
        T = np.asarray(fit.T_enu_map, dtype=np.float64)
        # ecef = R_ecef_map @ p_map + t_ecef
        self._r_ecef_map = r_enu_ecef.T @ T[:3, :3]
        self._t_ecef = r_enu_ecef.T @ T[:3, 3] + reference_ecef(fit.lla_ref)
        # cached and shared: pyproj's transformers are thread-safe (thread-local inside)
        self._transformer = CRS.of(GEOCENTRIC).transformer_to(self.crs)
        self.fast_chunks = 0
        self.fallback_chunks = 0

    def __repr__(self) -> str:
        return f"MapProjector(method={self.fit.method!r}, crs={self.crs.text[:40]!r})"

    # --- exact chain --------------------------------------------------------------------

    def map_to_ecef(self, xyz_map: ArrayLike) -> FloatArray:
        """Map-frame points ``(N, 3)`` -> ECEF ``(N, 3)`` (exact rotation + translation)."""
        return _as_points(xyz_map) @ self._r_ecef_map.T + self._t_ecef

    def ecef_to_map(self, ecef: ArrayLike) -> FloatArray:
        return (_as_points(ecef) - self._t_ecef) @ self._r_ecef_map

    def exact(self, xyz_map: ArrayLike) -> FloatArray:
        """Map-frame points -> ``(N, 3)`` CRS x, y and WGS 84 ellipsoidal height, exactly."""
        ecef = self.map_to_ecef(xyz_map)
        return self._transform(ecef, TransformDirection.FORWARD)

    def to_map(self, xyz_crs: ArrayLike) -> FloatArray:
        """Inverse of :meth:`exact`: CRS x, y, ellipsoidal height -> map frame."""
        ecef = self._transform(_as_points(xyz_crs), TransformDirection.INVERSE)
        return self.ecef_to_map(ecef)

    def to_lla(self, xyz_map: ArrayLike) -> FloatArray:
        """Map-frame points -> ``(N, 3)`` columns **lat, lon** (degrees), ellipsoidal height (m)."""
        ecef = self.map_to_ecef(xyz_map)
        lat, lon, alt = ecef_to_lla(ecef[:, 0], ecef[:, 1], ecef[:, 2])
        return np.stack([lat, lon, alt], axis=-1)

    def _transform(self, pts: FloatArray, direction: TransformDirection) -> FloatArray:
        if len(pts) == 0:
            return np.zeros((0, 3))
        try:
            x, y, z = self._transformer.transform(
                pts[:, 0], pts[:, 1], pts[:, 2], direction=direction, errcheck=True
            )
        except ProjError as exc:
            raise GeoreferenceError(f"projection to/from {self.crs.name!r} failed: {exc}") from exc
        return np.stack([np.asarray(x), np.asarray(y), np.asarray(z)], axis=-1).astype(
            np.float64, copy=False
        )

    # --- fast chunk path ----------------------------------------------------------------

    def linearise(self, xyz_map: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """The affine ``crs = (p - centre) @ A + b`` of one chunk; None when off by > 0.5 mm.

        Fitted by least squares on the exact transforms of the chunk's 3x3x3 bounding-box grid
        (corners, edge and face midpoints, centre) and verified on the same 27 points.
        Returns ``(centre, A (3, 3), b (3,))``.
        """
        pts = _as_points(xyz_map)
        # Column-wise reductions: ~20x faster than min(axis=0) on an (N, 3) C-order array.
        lo = np.array([pts[:, k].min() for k in range(3)])
        hi = np.array([pts[:, k].max() for k in range(3)])
        centre = 0.5 * (lo + hi)
        axes = [np.array([lo[k], centre[k], hi[k]]) for k in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        exact = self.exact(grid)
        origin = exact[13]  # the centre of the 3x3x3 grid
        design = np.hstack([grid - centre, np.ones((len(grid), 1))])
        coef, *_ = np.linalg.lstsq(design, exact - origin, rcond=None)
        deviation = np.abs(design @ coef - (exact - origin)).max()
        if not deviation <= FAST_TOLERANCE_M:
            return None
        return centre, coef[:3], coef[3] + origin

    def fast(
        self, xyz: ArrayLike, *, pose: ArrayLike | None = None, out: FloatArray | None = None
    ) -> FloatArray:
        """:meth:`exact` for one compact chunk (one payload, tens of metres) via a verified affine.

        With ``pose`` (T_map_base), ``xyz`` is in the base frame and the pose is composed into
        the affine: one pass base -> CRS. Within 1 mm of :meth:`exact`; chunks where the
        affine is not good to 0.5 mm at its check points (e.g. hundreds of metres across) fall
        back to :meth:`exact`. ``out`` (float64 (N, 3), may be ``xyz`` itself) receives the
        affine's result; the fall-back returns a new array.
        """
        pts = _as_points(xyz)
        t = None if pose is None else np.asarray(pose, dtype=np.float64)
        if len(pts) < _FAST_MIN_POINTS:
            return self.exact(pts if t is None else pts @ t[:3, :3].T + t[:3, 3])
        lo = np.array([pts[:, k].min() for k in range(3)])
        hi = np.array([pts[:, k].max() for k in range(3)])
        corners = np.array(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij")).reshape(3, -1).T
        if t is not None:
            corners = corners @ t[:3, :3].T + t[:3, 3]
        affine = self.linearise(corners)
        if affine is None:
            self.fallback_chunks += 1
            return self.exact(pts if t is None else pts @ t[:3, :3].T + t[:3, 3])
        self.fast_chunks += 1
        centre, a, b = affine
        matrix, offset = a, b - centre @ a
        if t is not None:  # p_map = p @ R^T + t, so crs = p @ (R^T A) + (t - centre) A + b
            matrix = t[:3, :3].T @ a
            offset = (t[:3, 3] - centre) @ a + b
        if out is None:
            out = np.empty_like(pts)
        # Per column (faster than an (N, 3) @ (3, 3) matmul), block by block of rows: the
        # block's results and temporaries stay in cache, and ``out`` may be ``pts``.
        rows = min(len(pts), _FAST_BLOCK_ROWS)
        block, product = np.empty((rows, 3)), np.empty(rows)
        for start in range(0, len(pts), rows):
            part = pts[start : start + rows]
            done, temp = block[: len(part)], product[: len(part)]
            x, y, z = part[:, 0], part[:, 1], part[:, 2]
            for k in range(3):
                column = done[:, k]
                np.multiply(x, matrix[0, k], out=column)
                column += np.multiply(y, matrix[1, k], out=temp)
                column += np.multiply(z, matrix[2, k], out=temp)
                column += offset[k]
            out[start : start + len(part)] = done
        return out

    def describe(self) -> dict[str, Any]:
        """CRS and vertical reference as JSON-ready text."""
        return {
            "crs": self.crs.text,
            "crs_name": self.crs.name,
            "vertical": "WGS 84 ellipsoidal height (m)",
        }


def projected_pose_xy(projector: MapProjector, poses_or_positions: ArrayLike) -> FloatArray:
    """Projected CRS x/y ``(N, 2)`` of node poses ``(N, 4, 4)`` or positions ``(N, 3)``, exact."""
    arr = np.asarray(poses_or_positions, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[1:] == (4, 4):
        arr = arr[:, :3, 3]
    elif arr.ndim == 2 and arr.shape == (4, 4):
        arr = arr[None, :3, 3]
    return projector.exact(arr)[:, :2]
