"""Fit the rigid transform that ties a SLAM map frame to a local ENU frame from GNSS fixes.

Pipeline (:func:`fit_georeference`):

1. Fixes with quality 0 or non-finite / out-of-range coordinates are *invalid*.
2. Valid fixes go to ENU around ``lla_ref`` (default: the earliest valid fix), exactly.
3. Time matching: the SLAM trajectory is interpolated linearly in time at each fix stamp.
   Fixes before/after the trajectory are *outside_trajectory*; fixes that fall between two
   trajectory stamps more than ``max_time_gap_s`` apart are *trajectory_gap*.
4. Each fix gets a horizontal sigma: its ``h_std`` when given (finite, > 0), else by fix
   quality (:data:`QUALITY_SIGMA_M`: RTK fixed 0.02 m, RTK float 0.2 m, DGPS 0.7 m, GPS 2.0 m,
   other non-zero qualities 5.0 m). Vertical sigma: ``v_std`` when given, else 1.5 x the
   horizontal one. :data:`MODEL_SIGMA_M` (SLAM drift, time matching, antenna lever arm) is
   added in quadrature to both; weights are ``1 / sigma_eff**2``.
5. Robust estimation: MSAC-RANSAC over minimal 2-fix yaw-2D samples (inlier threshold
   3.44 sigma_eff, the 99.73 % point of a 2-D Gaussian), then iterative weighted refits with
   trimming at 3.44 (horizontal) / 3 (vertical) sigma_eff, sigma scaled up by a robust
   variance factor (median of the normalised residuals over all matched fixes) when the
   stated sigmas are optimistic. Rejected matched fixes are *outlier*.
6. ``yaw2d``: rotation about z plus 3-D translation; closed-form weighted 2-D Procrustes for
   yaw and x/y, weighted mean of the height differences for z. ``rigid3d``: weighted 3-D
   Kabsch/Umeyama (no scale) starting from the ``yaw2d`` inliers.

``T_enu_map`` maps map-frame points into ENU: ``p_enu = R p_map + t``. Residuals are
"map position through the fit minus fix", in ENU metres.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from standgrid.errors import GeoreferenceError, InsufficientGnssError, PoorGeoreferenceError
from standgrid.geometry import Matrix4, invert_pose, transform_points, yaw_of
from standgrid.mission.posegraph import PoseGraph
from standgrid.mission.sensors import FixQuality, GnssFixes
from standgrid.stamps import NS_PER_S

from .enu import LLA, lla_to_enu
from .uncertainty import GeoreferenceUncertainty, fit_uncertainty

FloatArray = NDArray[np.float64]
Method = Literal["yaw2d", "rigid3d", "pose_graph"]
FIT_METHODS: tuple[str, ...] = ("yaw2d", "rigid3d")

#: Per-fix status names; ``GeoreferenceFit.status`` holds indices into this tuple.
FIX_STATUS: tuple[str, ...] = ("used", "invalid", "outside_trajectory", "trajectory_gap", "outlier")
USED, INVALID, OUTSIDE, GAP, OUTLIER = range(5)

#: Horizontal 1-sigma (m) by NMEA fix quality, used when a fix has no ``h_std``.
QUALITY_SIGMA_M: dict[int, float] = {
    int(FixQuality.RTK_FIXED): 0.02,
    int(FixQuality.RTK_FLOAT): 0.2,
    int(FixQuality.DGPS): 0.7,
    int(FixQuality.GPS): 2.0,
}
#: Sigma for other non-zero qualities (3 PPS, 6 dead reckoning, 7 manual, 8 simulation).
OTHER_QUALITY_SIGMA_M = 5.0
#: Vertical sigma = this x horizontal sigma when a fix has no ``v_std``.
VERTICAL_SIGMA_FACTOR = 1.5
#: Model error (SLAM drift, time matching, lever arm) added in quadrature to every sigma.
MODEL_SIGMA_M = 0.05
#: Trimming thresholds in sigmas: 99.73 % points of 2-D and 1-D Gaussians.
K_HORIZONTAL = math.sqrt(-2.0 * math.log(1.0 - 0.9973))  # 3.44
K_VERTICAL = 3.0
_CHI2_2DOF_MEDIAN = 2.0 * math.log(2.0)
_NORMAL_ABS_MEDIAN = 0.6744897501960817
#: Fixes must span at least this far (m, horizontally) for yaw to be observable.
MIN_SPREAD_M = 1.0
DEFAULT_MAX_TIME_GAP_S = 5.0
_RANSAC_MAX_HYPOTHESES = 1000
_MAX_REFINE_ITERATIONS = 50


@dataclass(frozen=True, eq=False)
class GeoreferenceFit:
    """A fitted map -> ENU transform with its per-fix diagnostics (arrays have one row per fix)."""

    lla_ref: LLA
    T_enu_map: Matrix4
    method: str
    fix_stamps_ns: NDArray[np.int64]
    residuals_m: FloatArray
    inliers: NDArray[np.bool_]
    status: NDArray[np.int8]
    weights: FloatArray
    rmse_m: float
    rmse_vertical_m: float
    n_used: int
    n_rejected: int
    #: 1-sigma of yaw and translation (GNSS fits; None for given transforms and anchors).
    uncertainty: GeoreferenceUncertainty | None = None

    @property
    def T_map_enu(self) -> Matrix4:
        """Inverse transform: ENU -> map (``GNSS_LLA_TO_MAP`` of a pose graph)."""
        return invert_pose(self.T_enu_map)

    @property
    def yaw_rad(self) -> float:
        """Heading of the map x axis in ENU (radians, counter-clockwise from East)."""
        return float(yaw_of(self.T_enu_map))

    @property
    def yaw_deg(self) -> float:
        return math.degrees(self.yaw_rad)

    @property
    def translation(self) -> FloatArray:
        """ENU position ``(3,)`` of the map origin."""
        return np.asarray(self.T_enu_map[:3, 3], dtype=np.float64).copy()

    @property
    def rejected_by_reason(self) -> dict[str, int]:
        """Counts of not-used fixes by reason (every reason present, zeros included)."""
        counts = np.bincount(self.status.astype(np.int64), minlength=len(FIX_STATUS))
        return {name: int(counts[i]) for i, name in enumerate(FIX_STATUS) if i != USED}

    @property
    def status_names(self) -> list[str]:
        return [FIX_STATUS[int(s)] for s in self.status]

    def map_to_enu(self, xyz_map: ArrayLike) -> FloatArray:
        """Map-frame points ``(N, 3)`` -> ENU ``(N, 3)``."""
        return transform_points(self.T_enu_map, xyz_map)

    @classmethod
    def without_fixes(cls, lla_ref: LLA, T_enu_map: Matrix4, method: str) -> GeoreferenceFit:
        """A transform given, not fitted (pose-graph anchor, hand-given anchor): no fixes."""
        return cls(
            lla_ref=lla_ref,
            T_enu_map=T_enu_map,
            method=method,
            fix_stamps_ns=np.zeros(0, dtype=np.int64),
            residuals_m=np.zeros((0, 3)),
            inliers=np.zeros(0, dtype=bool),
            status=np.zeros(0, dtype=np.int8),
            weights=np.zeros(0),
            rmse_m=math.nan,
            rmse_vertical_m=math.nan,
            n_used=0,
            n_rejected=0,
        )

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (strict JSON: NaN becomes ``None``); floats round-trip exactly."""
        return {
            "format": "standgrid.georeference/1",
            "method": self.method,
            "lla_ref": [float(v) for v in self.lla_ref],
            "T_enu_map": [[float(v) for v in row] for row in np.asarray(self.T_enu_map)],
            "rmse_m": _float_or_none(self.rmse_m),
            "rmse_vertical_m": _float_or_none(self.rmse_vertical_m),
            "n_used": int(self.n_used),
            "n_rejected": int(self.n_rejected),
            "rejected": self.rejected_by_reason,
            "fixes": {
                "stamps_ns": [int(s) for s in self.fix_stamps_ns],
                "residuals_m": [
                    None if not np.all(np.isfinite(r)) else [float(v) for v in r]
                    for r in self.residuals_m
                ],
                "inliers": [bool(b) for b in self.inliers],
                "status": self.status_names,
                "weights": [float(w) for w in self.weights],
            },
            "uncertainty": None if self.uncertainty is None else self.uncertainty.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> GeoreferenceFit:
        """Inverse of :meth:`to_dict`; raises :class:`GeoreferenceError` on malformed input."""
        try:
            fixes = data["fixes"]
            n = len(fixes["stamps_ns"])
            residuals = np.full((n, 3), np.nan)
            for i, r in enumerate(fixes["residuals_m"]):
                if r is not None:
                    residuals[i] = [float(v) for v in r]
            status = np.array([FIX_STATUS.index(s) for s in fixes["status"]], dtype=np.int8)
            lat, lon, alt = (float(v) for v in data["lla_ref"])
            fit = cls(
                lla_ref=(lat, lon, alt),
                T_enu_map=np.array(data["T_enu_map"], dtype=np.float64).reshape(4, 4),
                method=str(data["method"]),
                fix_stamps_ns=np.array(fixes["stamps_ns"], dtype=np.int64).reshape(n),
                residuals_m=residuals,
                inliers=np.array(fixes["inliers"], dtype=bool).reshape(n),
                status=status.reshape(n),
                weights=np.array(fixes["weights"], dtype=np.float64).reshape(n),
                rmse_m=_nan_if_none(data["rmse_m"]),
                rmse_vertical_m=_nan_if_none(data["rmse_vertical_m"]),
                n_used=int(data["n_used"]),
                n_rejected=int(data["n_rejected"]),
                uncertainty=_uncertainty_from_dict(data.get("uncertainty")),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise GeoreferenceError(f"malformed georeference dict: {exc!r}") from exc
        if fit.n_used + fit.n_rejected != n or int(fit.inliers.sum()) != fit.n_used:
            raise GeoreferenceError(
                f"inconsistent georeference dict: n_used={fit.n_used}, "
                f"n_rejected={fit.n_rejected}, {n} fixes"
            )
        return fit


def _float_or_none(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _nan_if_none(v: float | None) -> float:
    return math.nan if v is None else float(v)


# --- preparing fixes ---------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Prepared:
    ref: LLA
    stamps_ns: NDArray[np.int64]
    status: NDArray[np.int8]  # USED for usable (matched) fixes at this stage
    enu: FloatArray  # (n, 3), NaN for invalid
    p_map: FloatArray  # (n, 3), NaN for unmatched
    sigma_h: FloatArray  # effective (model sigma included)
    sigma_v: FloatArray

    @property
    def usable(self) -> NDArray[np.bool_]:
        return self.status == USED


def fix_sigmas(
    quality: ArrayLike, h_std: ArrayLike | None, v_std: ArrayLike | None = None
) -> tuple[FloatArray, FloatArray]:
    """Stated horizontal and vertical 1-sigma (m) per fix, before the model sigma is added."""
    q = np.asarray(quality).astype(np.int64)
    by_quality = np.array(
        [QUALITY_SIGMA_M.get(int(v), OTHER_QUALITY_SIGMA_M) for v in q], dtype=np.float64
    )
    sigma_h = by_quality
    if h_std is not None:
        h = np.asarray(h_std, dtype=np.float64)
        sigma_h = np.where(np.isfinite(h) & (h > 0), h, by_quality)
    sigma_v = VERTICAL_SIGMA_FACTOR * sigma_h
    if v_std is not None:
        v = np.asarray(v_std, dtype=np.float64)
        sigma_v = np.where(np.isfinite(v) & (v > 0), v, sigma_v)
    return sigma_h, sigma_v


def interpolate_trajectory(
    traj_stamps_ns: ArrayLike, traj_positions: ArrayLike, query_ns: ArrayLike, max_gap_ns: int
) -> tuple[FloatArray, NDArray[np.int8]]:
    """Positions at ``query_ns`` (linear in time) and a status per query (USED, OUTSIDE or GAP)."""
    t = np.asarray(traj_stamps_ns, dtype=np.int64)
    p = np.asarray(traj_positions, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(query_ns, dtype=np.int64)
    out = np.full((len(q), 3), np.nan)
    status = np.full(len(q), OUTSIDE, dtype=np.int8)
    if len(t) == 0 or len(q) == 0:
        return out, status
    order = np.argsort(t, kind="stable")
    t, p = t[order], p[order]
    inside = (q >= t[0]) & (q <= t[-1])
    hi = np.clip(np.searchsorted(t, q, side="left"), 0, len(t) - 1)
    lo = np.clip(hi - 1, 0, len(t) - 1)
    exact = t[hi] == q
    lo = np.where(exact, hi, lo)
    gap = t[hi] - t[lo]
    gap_bad = inside & ~exact & (gap > max_gap_ns)
    ok = inside & ~gap_bad
    frac = np.zeros(len(q))
    moving = ok & (gap > 0)
    frac[moving] = (q[moving] - t[lo[moving]]).astype(np.float64) / gap[moving].astype(np.float64)
    out[ok] = p[lo[ok]] + frac[ok, None] * (p[hi[ok]] - p[lo[ok]])
    status[ok] = USED
    status[gap_bad] = GAP
    return out, status


def _prepare(
    fixes: GnssFixes,
    traj_stamps_ns: ArrayLike,
    traj_positions_map: ArrayLike,
    max_time_gap_s: float,
    lla_ref: LLA | None,
    source: Path | None,
) -> _Prepared:
    stamps = np.asarray(fixes.stamps_ns, dtype=np.int64).ravel()
    cols = [np.asarray(c, dtype=np.float64).ravel() for c in (fixes.lat, fixes.lon, fixes.alt)]
    qual = np.asarray(fixes.quality).astype(np.int64).ravel()
    h_std, v_std = fixes.h_std, fixes.v_std
    n = len(stamps)
    lengths = {len(c) for c in cols} | {len(qual)}
    for extra in (h_std, v_std):
        lengths.add(len(np.asarray(extra).ravel()))
    if lengths != {n}:
        raise GeoreferenceError(
            f"GNSS columns differ in length ({sorted(lengths | {n})})", path=source
        )
    traj_t = np.asarray(traj_stamps_ns, dtype=np.int64).ravel()
    traj_p = np.asarray(traj_positions_map, dtype=np.float64)
    if traj_p.shape != (len(traj_t), 3):
        raise GeoreferenceError(
            f"trajectory positions {traj_p.shape} do not match {len(traj_t)} stamps", path=source
        )
    la, lo, al = cols
    valid = (
        (qual != int(FixQuality.INVALID))
        & np.isfinite(la)
        & np.isfinite(lo)
        & np.isfinite(al)
        & (np.abs(la) <= 90.0)
        & (np.abs(lo) <= 180.0)
    )
    status = np.full(n, INVALID, dtype=np.int8)
    if lla_ref is None:
        if not valid.any():
            raise InsufficientGnssError(
                f"{n} GNSS fixes, none valid (quality 0 or non-finite): cannot georeference",
                path=source,
            )
        first = int(np.flatnonzero(valid)[np.argmin(stamps[valid])])
        lla_ref = (float(la[first]), float(lo[first]), float(al[first]))
    else:
        lla_ref = (float(lla_ref[0]), float(lla_ref[1]), float(lla_ref[2]))
    enu = np.full((n, 3), np.nan)
    if valid.any():
        e, nn, u = lla_to_enu(la[valid], lo[valid], al[valid], lla_ref)
        enu[valid] = np.stack([e, nn, u], axis=-1)
    p_map = np.full((n, 3), np.nan)
    max_gap_ns = round(max_time_gap_s * NS_PER_S)
    matched, match_status = interpolate_trajectory(traj_t, traj_p, stamps[valid], max_gap_ns)
    p_map[valid] = matched
    status[valid] = match_status
    sh, sv = fix_sigmas(qual, h_std, v_std)
    return _Prepared(
        ref=lla_ref,
        stamps_ns=stamps,
        status=status,
        enu=enu,
        p_map=p_map,
        sigma_h=np.hypot(sh, MODEL_SIGMA_M),
        sigma_v=np.hypot(sv, MODEL_SIGMA_M),
    )


# --- closed-form solvers -----------------------------------------------------------------


def solve_yaw2d(
    p_map: FloatArray,
    q_enu: FloatArray,
    w_h: FloatArray,
    w_v: FloatArray,
    *,
    robust_z: bool = False,
) -> Matrix4:
    """Weighted rotation about z + translation mapping ``p_map`` onto ``q_enu`` (closed form).

    Yaw and x/y: weighted 2-D Procrustes; z offset: weighted mean of the height differences
    (weighted median when ``robust_z``).
    """
    wh = w_h / w_h.sum()
    cp, cq = wh @ p_map[:, :2], wh @ q_enu[:, :2]
    a, b = p_map[:, :2] - cp, q_enu[:, :2] - cq
    dot = wh @ (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])
    cross = wh @ (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    yaw = math.atan2(cross, dot)
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s], [s, c]])
    dz = q_enu[:, 2] - p_map[:, 2]
    tz = weighted_median(dz, w_v) if robust_z else float((w_v @ dz) / w_v.sum())
    T = np.eye(4)
    T[:2, :2] = rot
    T[:2, 3] = cq - rot @ cp
    T[2, 3] = tz
    return T


def solve_rigid3d(p_map: FloatArray, q_enu: FloatArray, w: FloatArray) -> Matrix4:
    """Weighted 3-D Kabsch/Umeyama without scale: the motion taking ``p_map`` onto ``q_enu``."""
    wn = w / w.sum()
    cp, cq = wn @ p_map, wn @ q_enu
    h = (p_map - cp).T @ ((q_enu - cq) * wn[:, None])
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    T = np.eye(4)
    T[:3, :3] = rot
    T[:3, 3] = cq - rot @ cp
    return T


def weighted_median(values: FloatArray, weights: FloatArray) -> float:
    """The weighted median (lower one at an exact half split); ValueError when empty."""
    if len(values) == 0:
        raise ValueError("weighted median of no values")
    order = np.argsort(values, kind="stable")
    cw = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cw, 0.5 * cw[-1])])


def _ransac_yaw2d(
    p: FloatArray, q: FloatArray, sigma_h: FloatArray, seed: int = 0
) -> NDArray[np.bool_]:
    """MSAC over 2-fix samples: the horizontal inlier set of the best yaw-2D hypothesis."""
    m = len(p)
    thr = K_HORIZONTAL * sigma_h
    n_pairs = m * (m - 1) // 2
    if n_pairs <= _RANSAC_MAX_HYPOTHESES:
        i, j = np.triu_indices(m, k=1)
    else:
        rng = np.random.default_rng(seed)
        i = rng.integers(0, m, _RANSAC_MAX_HYPOTHESES)
        j = (i + rng.integers(1, m, _RANSAC_MAX_HYPOTHESES)) % m
    dp, dq = p[j, :2] - p[i, :2], q[j, :2] - q[i, :2]
    base = np.hypot(dp[:, 0], dp[:, 1])
    good = base > np.maximum(0.5, 2.0 * (sigma_h[i] + sigma_h[j]))
    if not good.any():
        good = base > 1e-6
    if not good.any():
        return np.ones(m, dtype=bool)
    i, j, dp, dq = i[good], j[good], dp[good], dq[good]
    yaw = np.arctan2(
        dp[:, 0] * dq[:, 1] - dp[:, 1] * dq[:, 0], dp[:, 0] * dq[:, 0] + dp[:, 1] * dq[:, 1]
    )
    c, s = np.cos(yaw), np.sin(yaw)
    best_cost, best_inl = np.inf, np.ones(m, dtype=bool)
    for start in range(0, len(yaw), 100):
        sl = slice(start, start + 100)
        cs, ss = c[sl, None], s[sl, None]

        def rot(
            xy: FloatArray, cs: FloatArray = cs, ss: FloatArray = ss
        ) -> tuple[FloatArray, FloatArray]:
            return cs * xy[..., 0] - ss * xy[..., 1], ss * xy[..., 0] + cs * xy[..., 1]

        mid_p = 0.5 * (p[i[sl], :2] + p[j[sl], :2])
        mid_q = 0.5 * (q[i[sl], :2] + q[j[sl], :2])
        rx, ry = rot(mid_p[:, None, :])
        tx, ty = mid_q[:, 0:1] - rx, mid_q[:, 1:2] - ry
        px, py = rot(p[None, :, :2])
        r2 = (px + tx - q[None, :, 0]) ** 2 + (py + ty - q[None, :, 1]) ** 2
        cost = np.minimum(r2 / thr[None, :] ** 2, 1.0).sum(axis=1)
        k = int(np.argmin(cost))
        if cost[k] < best_cost:
            best_cost, best_inl = float(cost[k]), r2[k] <= thr**2
    return best_inl


def _variance_factor(normalised_sq: FloatArray, median_ref: float) -> float:
    """Robust variance factor (>= 1) from squared normalised residuals."""
    if len(normalised_sq) == 0:
        return 1.0
    return max(1.0, float(np.median(normalised_sq)) / median_ref)


def _trim(
    T: Matrix4, p: FloatArray, q: FloatArray, sh: FloatArray, sv: FloatArray
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Residuals of all matched fixes under ``T`` and the inlier mask at 3.44 / 3 sigma_eff."""
    res = transform_points(T, p) - q
    nh2 = (res[:, 0] ** 2 + res[:, 1] ** 2) / sh**2
    nv2 = res[:, 2] ** 2 / sv**2
    fh = _variance_factor(nh2, _CHI2_2DOF_MEDIAN)
    fv = _variance_factor(nv2, _NORMAL_ABS_MEDIAN**2)
    inl = (nh2 <= K_HORIZONTAL**2 * fh) & (nv2 <= K_VERTICAL**2 * fv)
    return res, inl


def _robust_fit(
    method: str,
    p: FloatArray,
    q: FloatArray,
    sh: FloatArray,
    sv: FloatArray,
    source: Path | None = None,
) -> tuple[Matrix4, NDArray[np.bool_]]:
    wh, wv = 1.0 / sh**2, 1.0 / sv**2
    inl = _ransac_yaw2d(p, q, sh)
    if inl.sum() < 2:  # no two fixes agree with the trajectory: nothing to fit
        raise InsufficientGnssError(
            f"the {len(p)} GNSS fixes matched to the trajectory are too scattered to fit a "
            f"georeference: no two of them agree with the trajectory's shape within "
            f"{K_HORIZONTAL:.2f} x their stated accuracy (median "
            f"{float(np.median(sh)):.2f} m); check the log (fixes of another place or time, "
            "wrong columns, no RTK fix)",
            path=source,
        )
    T = solve_yaw2d(p[inl], q[inl], wh[inl], wv[inl], robust_z=True)
    solvers = ["yaw2d"] if method == "yaw2d" else ["yaw2d", "rigid3d"]
    for solver in solvers:
        for _ in range(_MAX_REFINE_ITERATIONS):
            _, new = _trim(T, p, q, sh, sv)
            if new.sum() < 2:
                break
            if solver == "yaw2d":
                T = solve_yaw2d(p[new], q[new], wh[new], wv[new])
            else:
                T = solve_rigid3d(p[new], q[new], wh[new])
            if np.array_equal(new, inl):
                break
            inl = new
    _, inl = _trim(T, p, q, sh, sv)
    return T, inl


# --- public API ----------------------------------------------------------------------------


def _counts_message(status: NDArray[np.int8], n_good: int, min_fixes: int, max_gap_s: float) -> str:
    counts = np.bincount(status.astype(np.int64), minlength=len(FIX_STATUS))
    return (
        f"{len(status)} GNSS fixes: {counts[INVALID]} invalid (quality 0 / non-finite), "
        f"{counts[OUTSIDE]} outside the trajectory's time span, "
        f"{counts[GAP]} in trajectory gaps > {max_gap_s:g} s, {counts[OUTLIER]} outliers; "
        f"{n_good} good fixes < min_fixes={min_fixes}"
    )


def _assemble(
    prep: _Prepared, T: Matrix4, method: str, inl_usable: NDArray[np.bool_] | None
) -> GeoreferenceFit:
    """A fit with residuals for every matched fix; ``inl_usable`` None -> trim under ``T``."""
    usable = prep.usable
    n = len(prep.stamps_ns)
    residuals = np.full((n, 3), np.nan)
    status = prep.status.copy()
    inliers = np.zeros(n, dtype=bool)
    if usable.any():
        res, trimmed = _trim(
            T, prep.p_map[usable], prep.enu[usable], prep.sigma_h[usable], prep.sigma_v[usable]
        )
        residuals[usable] = res
        inliers[usable] = trimmed if inl_usable is None else inl_usable
    status[usable & ~inliers] = OUTLIER
    weights = np.where(inliers, 1.0 / prep.sigma_h**2, 0.0)
    if inliers.any():
        r = residuals[inliers]
        rmse_h = float(np.sqrt(np.mean(r[:, 0] ** 2 + r[:, 1] ** 2)))
        rmse_v = float(np.sqrt(np.mean(r[:, 2] ** 2)))
    else:
        rmse_h = rmse_v = math.nan
    n_used = int(inliers.sum())
    return GeoreferenceFit(
        lla_ref=prep.ref,
        T_enu_map=np.asarray(T, dtype=np.float64),
        method=method,
        fix_stamps_ns=prep.stamps_ns,
        residuals_m=residuals,
        inliers=inliers,
        status=status,
        weights=weights,
        rmse_m=rmse_h,
        rmse_vertical_m=rmse_v,
        n_used=n_used,
        n_rejected=n - n_used,
    )


def fit_georeference(
    fixes: GnssFixes,
    traj_stamps_ns: ArrayLike,
    traj_positions_map: ArrayLike,
    *,
    method: str = "yaw2d",
    min_fixes: int = 10,
    max_time_gap_s: float = DEFAULT_MAX_TIME_GAP_S,
    lla_ref: LLA | None = None,
    source: Path | None = None,
) -> GeoreferenceFit:
    """Fit ``T_enu_map`` from GNSS ``fixes`` and the SLAM trajectory (see the module docstring).

    Std columns of ``fixes`` that are NaN (or <= 0) fall back to the fix quality's sigma.
    ``source`` (default: the file the fixes came from) is named in errors.
    Raises :class:`InsufficientGnssError` (naming ``source`` and the counts of invalid,
    unmatched and outlier fixes) when fewer than ``min_fixes`` good fixes remain, or when the
    good fixes span less than :data:`MIN_SPREAD_M` (yaw unobservable); ``rigid3d`` also
    needs a trajectory that is not a straight line.
    """
    source = fixes.source if source is None else source
    if method not in FIT_METHODS:
        raise GeoreferenceError(
            f"unknown georeference method {method!r}; use one of {FIT_METHODS}", path=source
        )
    prep = _prepare(fixes, traj_stamps_ns, traj_positions_map, max_time_gap_s, lla_ref, source)
    usable = prep.usable
    n_usable = int(usable.sum())
    if n_usable < max(min_fixes, 2):
        raise InsufficientGnssError(
            _counts_message(prep.status, n_usable, min_fixes, max_time_gap_s), path=source
        )
    p, q = prep.p_map[usable], prep.enu[usable]
    sh, sv = prep.sigma_h[usable], prep.sigma_v[usable]
    T, inl = _robust_fit(method, p, q, sh, sv, source)
    fit = _assemble(prep, T, method, inl)
    if fit.n_used < min_fixes:
        raise InsufficientGnssError(
            _counts_message(fit.status, fit.n_used, min_fixes, max_time_gap_s), path=source
        )
    good = p[inl]
    centred = good - good.mean(axis=0)
    spread = float(np.max(np.hypot(centred[:, 0], centred[:, 1])))
    if spread < MIN_SPREAD_M:
        raise InsufficientGnssError(
            f"the {fit.n_used} good GNSS fixes span only {spread:.2f} m of trajectory: "
            f"yaw is unobservable (need >= {MIN_SPREAD_M} m)",
            path=source,
        )
    if method == "rigid3d":
        sv_axes = np.linalg.svd(centred, compute_uv=False) / math.sqrt(len(good))
        if sv_axes[1] < MIN_SPREAD_M:
            raise InsufficientGnssError(
                f"the good GNSS fixes lie along a line (second extent {sv_axes[1]:.2f} m): "
                "roll/pitch are unobservable, use method='yaw2d'",
                path=source,
            )
    stamps = prep.stamps_ns[usable][inl]
    return _with_uncertainty(fit, p[inl], q[inl], sh[inl], sv[inl], stamps)


def evaluate_georeference(
    T_enu_map: Matrix4,
    lla_ref: LLA,
    method: str,
    fixes: GnssFixes,
    traj_stamps_ns: ArrayLike,
    traj_positions_map: ArrayLike,
    *,
    max_time_gap_s: float = DEFAULT_MAX_TIME_GAP_S,
    source: Path | None = None,
) -> GeoreferenceFit:
    """Residuals and outlier flags of GNSS ``fixes`` under a *given* transform (nothing is
    refitted)."""
    source = fixes.source if source is None else source
    prep = _prepare(fixes, traj_stamps_ns, traj_positions_map, max_time_gap_s, lla_ref, source)
    return _assemble(prep, np.asarray(T_enu_map, dtype=np.float64), method, None)


def fit_from_pose_graph(graph: PoseGraph) -> GeoreferenceFit | None:
    """The georeference a pose graph carries (``GNSS_LLA_REF`` + ``GNSS_LLA_TO_MAP``), else None."""
    if graph.gnss_lla_ref is None or graph.gnss_lla_to_map is None:
        return None
    T_map_enu = np.asarray(graph.gnss_lla_to_map, dtype=np.float64)
    if T_map_enu.shape != (4, 4) or not np.all(np.isfinite(T_map_enu)):
        raise GeoreferenceError("GNSS_LLA_TO_MAP is not a finite 4x4 pose", path=graph.source)
    lat, lon, alt = (float(v) for v in graph.gnss_lla_ref)
    return GeoreferenceFit.without_fixes((lat, lon, alt), invert_pose(T_map_enu), "pose_graph")


# --- uncertainty (standgrid.georeference.uncertainty) ----------------------------------------


def _with_uncertainty(
    fit: GeoreferenceFit,
    p: FloatArray,
    q: FloatArray,
    sh: FloatArray,
    sv: FloatArray,
    stamps_ns: NDArray[np.int64],
) -> GeoreferenceFit:
    """``fit`` with the 1-sigma uncertainty of its transform over its inlier fixes."""
    from dataclasses import replace

    uncertainty = fit_uncertainty(fit.T_enu_map, p, q, sh, sv, fit.method, stamps_ns)
    return replace(fit, uncertainty=uncertainty)


def _uncertainty_from_dict(data: Mapping[str, Any] | None) -> GeoreferenceUncertainty | None:
    return None if data is None else GeoreferenceUncertainty.from_dict(data)


#: A fit is refused when its horizontal RMSE exceeds this many times the RMSE its fixes'
#: stated accuracy predicts (sqrt(2) x their RMS horizontal sigma, model sigma included).
MAX_RMSE_RATIO = 10.0


def check_fit_quality(
    fit: GeoreferenceFit, *, max_ratio: float = MAX_RMSE_RATIO, source: Path | None = None
) -> None:
    """Refuse a fit whose residuals are far beyond the fixes' stated accuracy.

    The expected horizontal RMSE of fixes with 1-sigma ``s_i`` (2-D Gaussian) is
    ``sqrt(2) * rms(s_i)``; a fit whose RMSE exceeds ``max_ratio`` times that raises
    :class:`PoorGeoreferenceError` saying both figures. Fits without fixes pass.
    """
    used = fit.inliers & (fit.weights > 0)
    if not used.any() or not math.isfinite(fit.rmse_m):
        return
    sigma = 1.0 / np.sqrt(fit.weights[used])
    expected = math.sqrt(2.0) * float(np.sqrt(np.mean(sigma**2)))
    if fit.rmse_m > max_ratio * expected:
        raise PoorGeoreferenceError(
            f"georeference ({fit.method}) has a horizontal RMSE of {fit.rmse_m:.3f} m over "
            f"{int(used.sum())} fixes, {fit.rmse_m / expected:.0f}x the {expected:.3f} m their "
            f"stated accuracy allows (limit {max_ratio:g}x): the GNSS fixes do not fit the "
            "trajectory (wrong or displaced fixes, or another mission's log); fix the log, or "
            "accept it explicitly (option accept_poor_georeference)",
            path=source,
            option="accept_poor_georeference",
        )
