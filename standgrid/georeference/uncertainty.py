"""How well a GNSS fit ties the map frame to the Earth: 1-sigma of yaw and translation.

The covariance of the fitted parameters comes from the linearised weighted least-squares
problem at the solution, over the inlier fixes only:

- ``yaw2d``: parameters (yaw, t_E, t_N, t_U); a fix gives two horizontal rows
  ``d(R p + t)/d(yaw, t_E, t_N)`` with weight ``1 / sigma_h**2`` and one vertical row
  ``d/dt_U`` with weight ``1 / sigma_v**2`` (the fit's own weights, model sigma included);
- ``rigid3d``: parameters (three small rotations about E, N, U applied after the fitted
  rotation, t_E, t_N, t_U); yaw is the rotation about U.

The weights are scaled by *a posteriori* variance factors (weighted residual sum of squares
over the degrees of freedom, horizontal and vertical apart), so the sigma follows the
scatter the fixes actually show, not only what they state. The covariance is then
``(J^T W J)^-1``. It assumes independent fix errors; errors correlated over time (multipath
under one tree, a slowly drifting float solution) make it optimistic.

Translation is that of the map origin (``T_enu_map[:3, 3]``); far from the fixes the yaw
sigma dominates, so ``sigma_horizontal_max_m`` gives the largest horizontal 1-sigma of a
trajectory position matched to a fix.

A heading is *not fixed* when its 1-sigma exceeds :data:`MAX_YAW_SIGMA_DEG`: then
:attr:`GeoreferenceUncertainty.warnings` says so and names the GNSS baseline (the largest
horizontal distance between two inlier fixes' trajectory positions).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Yaw 1-sigma (degrees) above which the heading counts as not fixed by the GNSS (0.5 deg is
#: 0.87 m of sideways error 100 m from the fixes).
MAX_YAW_SIGMA_DEG = 0.5


@dataclass(frozen=True)
class GeoreferenceUncertainty:
    """1-sigma uncertainty of a georeference fit (see the module docstring)."""

    sigma_yaw_deg: float
    #: E, N, U 1-sigma (m) of the map origin's ENU position.
    sigma_translation_m: tuple[float, float, float]
    #: Largest horizontal 1-sigma (m) of a fix-matched trajectory position under the fit.
    sigma_horizontal_max_m: float
    #: Largest horizontal distance (m) between two inlier fixes' trajectory positions.
    baseline_m: float
    #: Covariance of (yaw rad, t_E, t_N, t_U).
    covariance: tuple[tuple[float, ...], ...]
    method: str = "covariance"
    warnings: tuple[str, ...] = ()

    @property
    def heading_fixed(self) -> bool:
        return self.sigma_yaw_deg <= MAX_YAW_SIGMA_DEG

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "sigma_yaw_deg": _json_float(self.sigma_yaw_deg),
            "sigma_translation_m": [_json_float(v) for v in self.sigma_translation_m],
            "sigma_horizontal_max_m": _json_float(self.sigma_horizontal_max_m),
            "baseline_m": _json_float(self.baseline_m),
            "covariance": [[_json_float(v) for v in row] for row in self.covariance],
            "warnings": list(self.warnings),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> GeoreferenceUncertainty:
        e, n, u = (_float(v) for v in data["sigma_translation_m"])
        return cls(
            sigma_yaw_deg=_float(data["sigma_yaw_deg"]),
            sigma_translation_m=(e, n, u),
            sigma_horizontal_max_m=_float(data["sigma_horizontal_max_m"]),
            baseline_m=_float(data["baseline_m"]),
            covariance=tuple(tuple(_float(v) for v in row) for row in data["covariance"]),
            method=str(data.get("method", "covariance")),
            warnings=tuple(str(w) for w in data.get("warnings", ())),
        )


def _json_float(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _float(v: Any) -> float:
    return math.nan if v is None else float(v)


def _skew(v: FloatArray) -> FloatArray:
    """Rows of ``-[v]x`` for each vector of ``v`` (n, 3) -> (n, 3, 3)."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = v[:, 2], -v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = -v[:, 2], v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = v[:, 1], -v[:, 0]
    return out


def fit_uncertainty(
    T_enu_map: FloatArray,
    p_map: FloatArray,
    q_enu: FloatArray,
    sigma_h: FloatArray,
    sigma_v: FloatArray,
    method: str,
    stamps_ns: NDArray[np.int64] | None = None,
    block_s: float = 60.0,
) -> GeoreferenceUncertainty:
    """The 1-sigma uncertainty of ``T_enu_map`` fitted to inlier fixes ``q_enu`` at trajectory
    positions ``p_map`` with effective sigmas ``sigma_h`` / ``sigma_v`` (module docstring)."""
    T = np.asarray(T_enu_map, dtype=np.float64)
    p = np.asarray(p_map, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(q_enu, dtype=np.float64).reshape(-1, 3)
    n = len(p)
    rp = p @ T[:3, :3].T  # rotated positions, before translation
    res = rp + T[:3, 3] - q
    wh, wv = 1.0 / np.asarray(sigma_h) ** 2, 1.0 / np.asarray(sigma_v) ** 2
    if method == "rigid3d":
        n_h, n_v = 4, 2  # (rotations, tE, tN) / (rotations about E, N, tU), approximately
        jac = np.zeros((n, 3, 6))
        jac[:, :, :3] = _skew(rp)  # d(exp([phi]x) R p)/d(phi) = -[R p]x
        jac[:, :, 3:] = np.eye(3)
        yaw_index = 2
    else:
        n_h, n_v = 3, 1
        jac = np.zeros((n, 3, 4))
        jac[:, 0, 0], jac[:, 1, 0] = -rp[:, 1], rp[:, 0]  # d(R(yaw) p)/d(yaw)
        jac[:, :, 1:] = np.eye(3)
        yaw_index = 0
    fh = _variance_factors(wh * (res[:, 0] ** 2 + res[:, 1] ** 2), 2, n_h, sigma_h)
    fv = _variance_factors(wv * res[:, 2] ** 2, 1, n_v, sigma_h)
    w = np.column_stack([wh / fh, wh / fh, wv / fv])  # (n, 3)
    normal = np.einsum("nik,ni,nil->kl", jac, w, jac)
    try:
        inv = np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        inv = np.full(normal.shape, np.inf)
    cov, how = inv, "covariance"
    if stamps_ns is not None and n:
        robust = _block_covariance(inv, jac, w, res, np.asarray(stamps_ns), block_s)
        if robust is not None and np.trace(robust) > np.trace(cov):
            cov, how = robust, f"block covariance ({block_s:g} s blocks)"
    if method == "rigid3d":  # report (yaw, tE, tN, tU) like yaw2d
        keep = [yaw_index, 3, 4, 5]
        cov = cov[np.ix_(keep, keep)]
    var = np.diag(cov)
    sigma_yaw = math.degrees(math.sqrt(max(float(var[0]), 0.0)))
    st = tuple(math.sqrt(max(float(v), 0.0)) for v in var[1:4])
    # horizontal covariance of each matched position: J_i C J_i^T (yaw and tE, tN only)
    j = np.zeros((n, 2, 4))
    j[:, 0, 0], j[:, 1, 0] = -rp[:, 1], rp[:, 0]
    j[:, 0, 1] = j[:, 1, 2] = 1.0
    pos_cov = np.einsum("nik,kl,njl->nij", j, cov, j)
    sigma_pos = np.sqrt(np.maximum(np.trace(pos_cov, axis1=1, axis2=2), 0.0))
    xy = p[:, :2]
    baseline = _baseline(xy)
    warnings: list[str] = []
    if not sigma_yaw <= MAX_YAW_SIGMA_DEG:
        warnings.append(
            f"GNSS baseline too short to fix the heading: the inlier fixes span {baseline:.1f} m "
            f"of trajectory, heading 1-sigma {sigma_yaw:.2f} deg (> {MAX_YAW_SIGMA_DEG} deg); "
            f"points 100 m from the fixes are placed to ~{math.radians(sigma_yaw) * 100:.1f} m "
            "(1-sigma) only: drive a longer GNSS-covered stretch, or give option anchor with a "
            "known heading"
        )
    return GeoreferenceUncertainty(
        sigma_yaw_deg=sigma_yaw,
        sigma_translation_m=(st[0], st[1], st[2]),
        sigma_horizontal_max_m=float(sigma_pos.max()) if n else math.nan,
        baseline_m=baseline,
        covariance=tuple(tuple(float(v) for v in row) for row in cov),
        method=how,
        warnings=tuple(warnings),
    )


#: Fixes of one accuracy class (a decade of stated sigma) needed for its own variance factor.
MIN_CLASS_FIXES = 10


def _variance_factors(wr2: FloatArray, rows: int, params: int, sigma_h: FloatArray) -> FloatArray:
    """A posteriori variance factor per fix: one per accuracy class (decade of the stated
    horizontal sigma: RTK fixed, float / DGPS, autonomous GPS) with enough fixes, else the
    overall one. ``wr2``: weighted squared residuals, ``rows`` per fix."""
    n = len(wr2)
    overall = float(wr2.sum()) / max(rows * n - params, 1)
    overall = overall if overall > 0 else 1.0  # no scatter at all: keep the stated sigmas
    out = np.full(n, overall)
    decade = np.floor(np.log10(np.asarray(sigma_h, dtype=np.float64)))
    classes = np.unique(decade)
    if len(classes) < 2:
        return out
    for c in classes:
        members = decade == c
        k = int(members.sum())
        if k >= MIN_CLASS_FIXES:
            share = params * k / n  # the parameters' share of this class's degrees of freedom
            factor = float(wr2[members].sum()) / max(rows * k - share, 1.0)
            out[members] = factor if factor > 0 else overall
    return out


#: Fewest time blocks for the block (cluster-robust) covariance to be used.
MIN_BLOCKS = 6


def _block_covariance(
    inv_normal: FloatArray,
    jac: FloatArray,
    w: FloatArray,
    res: FloatArray,
    stamps_ns: NDArray[np.int64],
    block_s: float,
) -> FloatArray | None:
    """Cluster-robust (sandwich) covariance over time blocks of ``block_s`` seconds: fix
    errors correlated within a block (SLAM drift, multipath, an RTK window) count once."""
    block = ((stamps_ns - stamps_ns.min()) // int(block_s * 1e9)).astype(np.int64)
    ids, index = np.unique(block, return_inverse=True)
    m = len(ids)
    if m < MIN_BLOCKS:
        return None
    score = np.einsum("nik,ni,ni->nk", jac, w, res)  # J_i^T W_i r_i
    g = np.zeros((m, score.shape[1]))
    np.add.at(g, index, score)
    meat = g.T @ g * (m / (m - 1))
    return np.asarray(inv_normal @ meat @ inv_normal)


def _baseline(xy: FloatArray) -> float:
    """Largest distance between two points (over the convex hull when there are many)."""
    if len(xy) < 2:
        return 0.0
    pts = xy
    if len(xy) > 50:
        from scipy.spatial import ConvexHull, QhullError

        try:
            pts = xy[ConvexHull(xy).vertices]
        except QhullError:  # collinear: the extreme points along the line
            centred = xy - xy.mean(axis=0)
            axis = np.linalg.svd(centred, full_matrices=False)[2][0]
            t = centred @ axis
            pts = xy[[int(np.argmin(t)), int(np.argmax(t))]]
    d = pts[:, None, :] - pts[None, :, :]
    return float(np.sqrt((d**2).sum(axis=-1)).max())
