"""One graph of missions, solved with GTSAM: each mission's placement corrected as a rigid
whole, from its GNSS prior and the registrations between missions.

Variables: one ``Pose2`` per mission, the horizontal correction ``G_i`` of its placement
(``q_true = R_i q + g_i`` with ``q`` a CRS point minus the graph's origin), and one height
offset per mission (a separate linear problem). Factors:

- **GNSS prior** about the mission's centroid: the fit's white-noise covariance scaled by
  the residuals' correlation (``n / n_eff``, ``n_eff = span / (2 tau)``, ``tau`` where the
  residuals' autocorrelation falls below 1/e) plus a **bias per recording**
  (``gnss_bias_m`` horizontal RMS; the fixes themselves cannot show it). Plain scans
  already in the CRS, and missions held as the reference, get a tight prior.
- **Registration** (:mod:`.register`): ``G_f^-1 G_m`` = the measured transform, with its
  covariance, under a Huber kernel.

The marginals give each mission's covariance; a point's horizontal 1-sigma is the DRMS
``sqrt(sigma_E^2 + sigma_N^2)``, at most over the mission's nodes (``sigma_h_m``), and
relative to the missions it was registered with (``sigma_rel_m``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid.alignment.register import Registration, rot2d

FloatArray = NDArray[np.float64]

#: Horizontal RMS (m) of a GNSS bias per recording under a canopy, and its vertical one.
GNSS_BIAS_M = 1.0
GNSS_BIAS_VERTICAL_M = 1.5
#: Prior of a placement held as it is (plain scans in the CRS, reference missions).
HELD_SIGMA_M = 0.001
HELD_SIGMA_YAW = 1e-6
#: Prior of a placement without GNSS (an anchor given by hand): loose.
ANCHOR_SIGMA_M = 5.0
ANCHOR_SIGMA_YAW = math.radians(5.0)
#: Prior of a mission without any placement (no GNSS, no anchor): none to speak of.
UNPLACED_SIGMA_M = 1e4
UNPLACED_SIGMA_YAW = 10.0
HUBER_K = 1.345
#: A fix weighted at least this (1 / sigma^2; sigma <= 0.1 m) is of RTK-fixed class.
RTK_WEIGHT = 100.0


@dataclass(frozen=True)
class Prior:
    """A mission's placement before alignment: 1-sigma (per axis, m) of its centroid, of
    its yaw (rad) and of its height, about ``centre`` (CRS x, y)."""

    centre: tuple[float, float]
    sigma_xy: float
    sigma_yaw: float
    sigma_z: float
    how: str

    def sigma_at(self, nodes: FloatArray) -> float:
        """The largest horizontal DRMS 1-sigma over ``nodes`` (same frame as ``centre``)."""
        if not len(nodes):
            return math.sqrt(2.0) * self.sigma_xy
        lever2 = np.sum((np.asarray(nodes)[:, :2] - np.asarray(self.centre)) ** 2, axis=1)
        return float(np.sqrt(2.0 * self.sigma_xy**2 + self.sigma_yaw**2 * lever2).max())


def correlation_time(stamps_ns: NDArray[np.int64], residuals: FloatArray) -> float:
    """Seconds until the residuals' autocorrelation falls below 1/e (E and N pooled)."""
    t = (stamps_ns - stamps_ns[0]) * 1e-9
    if len(t) > 2000:  # the pairs grow as n^2
        pick = np.linspace(0, len(t) - 1, 2000).astype(np.int64)
        t, residuals = t[pick], residuals[pick]
    r = residuals - residuals.mean(axis=0)
    var = float(np.mean(np.sum(r**2, axis=1)))
    span = float(t[-1] - t[0]) if len(t) else 0.0
    if var <= 0 or span <= 0:
        return 0.0
    lag = np.abs(t[:, None] - t[None, :])
    prod = r @ r.T
    step = max(span / 200.0, 1.0)
    bins = np.floor(lag / step).astype(np.int64).ravel()
    sums = np.bincount(bins, prod.ravel())
    counts = np.bincount(bins)
    acf = np.divide(sums, counts * var, out=np.zeros(len(sums)), where=counts > 0)
    usable = counts > 10
    below = np.flatnonzero(usable & (acf < 1.0 / math.e))
    return float(below[0] * step) if len(below) else span


def gnss_prior(
    fit: Any, nodes_map: FloatArray, centre_crs: FloatArray, bias_m: float = GNSS_BIAS_M
) -> Prior:
    """The prior of a GNSS-fitted placement (module doc); ``nodes_map``: the mission's
    trajectory in its map frame, ``centre_crs``: its centroid in the CRS."""
    centre = (float(centre_crs[0]), float(centre_crs[1]))
    unc = fit.uncertainty
    used = fit.inliers & np.all(np.isfinite(fit.residuals_m), axis=1)
    if unc is None or used.sum() < 3:
        return Prior(centre, ANCHOR_SIGMA_M, ANCHOR_SIGMA_YAW, ANCHOR_SIGMA_M, "anchor")
    res = fit.residuals_m[used]
    stamps = fit.fix_stamps_ns[used]
    n = len(res)
    span = float(stamps[-1] - stamps[0]) * 1e-9
    tau = correlation_time(stamps, res[:, :2])
    n_eff = min(float(n), max(1.0, span / (2.0 * tau))) if tau > 0 else float(n)
    scale = n / n_eff
    cov = np.asarray(unc.covariance, dtype=np.float64)  # (yaw, tE, tN, tU)
    # the centroid's scatter under correlated errors: s^2 / n_eff per axis; the heading from
    # the same scatter over the fixes' spread about their centre
    centred = res[:, :2] - res[:, :2].mean(axis=0)
    s2 = float(np.mean(np.sum(centred**2, axis=1))) / 2.0
    lever = np.asarray(nodes_map, dtype=np.float64)[:, :2]
    spread = float(np.mean(np.sum((lever - lever.mean(axis=0)) ** 2, axis=1)))
    white = max(s2 / n_eff, float(cov[1, 1] + cov[2, 2]) / 2.0)
    var_yaw = max(s2 / n_eff / max(spread, 1.0), float(cov[0, 0]))
    # fixes of centimetres (RTK fixed) carry the fit when they hold most of its weight
    weights = fit.weights[used]
    rtk = float(weights[weights >= RTK_WEIGHT].sum()) > 0.5 * float(weights.sum())
    bias = 0.02 if rtk else bias_m
    sigma_xy = math.sqrt(white + bias**2 / 2.0)
    sigma_yaw = math.sqrt(var_yaw)
    sigma_z = math.sqrt(float(cov[3, 3]) * scale + (0.03 if rtk else GNSS_BIAS_VERTICAL_M) ** 2)
    how = f"GNSS: {n} fixes, correlation {tau:.0f} s ({n_eff:.1f} independent), bias {bias:.2f} m"
    return Prior(centre, sigma_xy, sigma_yaw, sigma_z, how)


def placement_sigma(
    fit: Any, nodes_map: FloatArray, bias_m: float = GNSS_BIAS_M
) -> tuple[float, str] | None:
    """A GNSS placement's horizontal DRMS 1-sigma, the largest over the trajectory
    ``nodes_map``, with correlated errors and a bias per recording counted (the prior of
    :func:`gnss_prior`); None for a transform not fitted to fixes."""
    nodes = np.asarray(nodes_map, dtype=np.float64).reshape(-1, 3)
    if not len(nodes):
        return None
    prior = gnss_prior(fit, nodes, nodes.mean(axis=0), bias_m)
    return None if prior.how == "anchor" else (prior.sigma_at(nodes), prior.how)


def unplaced_prior(centre_crs: FloatArray) -> Prior:
    centre = (float(centre_crs[0]), float(centre_crs[1]))
    how = "no GNSS: placed by registration"
    return Prior(centre, UNPLACED_SIGMA_M, UNPLACED_SIGMA_YAW, UNPLACED_SIGMA_M, how)


def held_prior(centre_crs: FloatArray, how: str) -> Prior:
    return Prior(
        (float(centre_crs[0]), float(centre_crs[1])),
        HELD_SIGMA_M,
        HELD_SIGMA_YAW,
        HELD_SIGMA_M,
        how,
    )


@dataclass(frozen=True)
class Correction:
    """One mission's solved correction: ``p' = R(yaw) (p - origin) + origin + g`` (CRS,
    horizontal) and ``z + dz``; ``covariance`` of (g in body axes, yaw)."""

    origin: tuple[float, float]
    g: tuple[float, float]
    yaw: float
    dz: float
    covariance: FloatArray
    sigma_z: float

    def apply(self, xyz: FloatArray) -> FloatArray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        q = xyz[:, :2] - self.origin
        out = xyz.copy()
        out[:, 0] = c * q[:, 0] - s * q[:, 1] + self.origin[0] + self.g[0]
        out[:, 1] = s * q[:, 0] + c * q[:, 1] + self.origin[1] + self.g[1]
        out[:, 2] = xyz[:, 2] + self.dz
        return out

    def sigma_at(self, xy: FloatArray) -> FloatArray:
        """DRMS horizontal 1-sigma (m) at CRS points ``xy`` (n, 2)."""
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - self.origin
        j = np.zeros((len(q), 2, 3))
        j[:, 0, 0] = j[:, 1, 1] = 1.0
        j[:, 0, 2], j[:, 1, 2] = -q[:, 1], q[:, 0]
        cov = np.einsum("nik,kl,njl->nij", j, self.covariance, j)
        return np.sqrt(np.maximum(np.trace(cov, axis1=1, axis2=2), 0.0))


@dataclass(frozen=True)
class Solution:
    corrections: dict[str, Correction]
    #: name -> the largest relative DRMS 1-sigma to a mission it was registered with.
    sigma_rel: dict[str, float]
    #: name -> the GNSS prior's normalised residual (Mahalanobis, 3 dof).
    prior_misfit: dict[str, float]


def solve(
    names: list[str], priors: dict[str, Prior], registrations: list[Registration]
) -> Solution:
    """Optimise the mission graph (module doc)."""
    import gtsam

    origin = np.mean([priors[n].centre for n in names], axis=0)
    key = {n: gtsam.symbol("m", i) for i, n in enumerate(names)}
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for n in names:
        p = priors[n]
        c = np.asarray(p.centre) - origin
        # (t about the centroid, yaw) -> (g about the origin, yaw): g = t + (I - R) c
        j = np.eye(3)
        j[0, 2], j[1, 2] = c[1], -c[0]
        cov = j @ np.diag([p.sigma_xy**2, p.sigma_xy**2, p.sigma_yaw**2]) @ j.T
        graph.add(
            gtsam.PriorFactorPose2(
                key[n], gtsam.Pose2(0, 0, 0), gtsam.noiseModel.Gaussian.Covariance(cov)
            )
        )
    accepted = [r for r in registrations if r.accepted]
    measured: dict[tuple[str, str], Any] = {}
    for r in accepted:
        pv = np.asarray(r.pivot) - origin
        rot = rot2d(r.yaw)
        g = np.asarray(r.t) + pv - rot @ pv
        j = np.eye(3)
        j[:2, 2] = -np.array([[0.0, -1.0], [1.0, 0.0]]) @ rot @ pv
        cov = j @ np.asarray(r.covariance) @ j.T
        body = np.eye(3)
        body[:2, :2] = rot.T  # GTSAM's Pose2 tangent: translation in the body frame
        cov = body @ cov @ body.T
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K),
            gtsam.noiseModel.Gaussian.Covariance(cov),
        )
        graph.add(
            gtsam.BetweenFactorPose2(
                key[r.fixed], key[r.moving], gtsam.Pose2(g[0], g[1], r.yaw), noise
            )
        )
        measured[(r.fixed, r.moving)] = gtsam.Pose2(g[0], g[1], r.yaw)
    # start from the priors, and missions placed nowhere from what registers them
    start = {n: gtsam.Pose2(0, 0, 0) for n in names if priors[n].sigma_xy < UNPLACED_SIGMA_M}
    grown = True
    while grown:
        grown = False
        for (f, m), between in measured.items():
            if f in start and m not in start:
                start[m], grown = start[f].compose(between), True
            elif m in start and f not in start:
                start[f], grown = start[m].compose(between.inverse()), True
    for n in names:
        initial.insert(key[n], start.get(n, gtsam.Pose2(0, 0, 0)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    marginals = gtsam.Marginals(graph, result)
    thetas = {n: result.atPose2(key[n]).theta() for n in names}
    dz, sz = _heights(names, priors, accepted)
    corrections: dict[str, Correction] = {}
    for i, n in enumerate(names):
        pose = result.atPose2(key[n])
        cov = np.asarray(marginals.marginalCovariance(key[n]))
        rot = rot2d(pose.theta())
        world = np.eye(3)
        world[:2, :2] = rot
        corrections[n] = Correction(
            (float(origin[0]), float(origin[1])),
            (pose.x(), pose.y()),
            pose.theta(),
            float(dz[i]),
            world @ cov @ world.T,
            float(sz[i]),
        )
    sigma_rel: dict[str, float] = {n: math.nan for n in names}
    for r in accepted:
        joint = marginals.jointMarginalCovariance(gtsam.KeyVector([key[r.moving], key[r.fixed]]))
        full = np.asarray(joint.fullMatrix())
        world = np.eye(6)  # each block from its own body frame to the CRS axes
        world[:2, :2], world[3:5, 3:5] = rot2d(thetas[r.moving]), rot2d(thetas[r.fixed])
        full = world @ full @ world.T
        at = np.asarray(r.pivot) - origin
        jm = np.array([[1.0, 0.0, -at[1]], [0.0, 1.0, at[0]]])
        jj = np.hstack([jm, -jm])
        rel = float(math.sqrt(max(float(np.trace(jj @ full @ jj.T)), 0.0)))
        for n in (r.moving, r.fixed):
            sigma_rel[n] = rel if math.isnan(sigma_rel[n]) else max(sigma_rel[n], rel)
    misfit = {}
    for n in names:
        p, corr = priors[n], corrections[n]
        centre = np.array([p.centre])
        moved = corr.apply(np.column_stack([centre, [0.0]]))[0, :2] - centre[0]
        misfit[n] = float(math.hypot(*moved) / p.sigma_xy)
    return Solution(corrections, sigma_rel, misfit)


def _heights(
    names: list[str], priors: dict[str, Prior], accepted: list[Registration]
) -> tuple[FloatArray, FloatArray]:
    """Height offsets by weighted least squares: priors dz_i ~ 0, ``dz_m - dz_f = r.dz``."""
    index = {n: i for i, n in enumerate(names)}
    rows, rhs, w = [], [], []
    for n in names:
        a = np.zeros(len(names))
        a[index[n]] = 1.0
        rows.append(a)
        rhs.append(0.0)
        w.append(1.0 / priors[n].sigma_z ** 2)
    for r in accepted:
        a = np.zeros(len(names))
        a[index[r.moving]], a[index[r.fixed]] = 1.0, -1.0
        rows.append(a)
        rhs.append(r.dz)
        w.append(1.0 / r.sigma_z**2)
    A, b, W = np.array(rows), np.array(rhs), np.array(w)
    normal = A.T @ (A * W[:, None])
    cov = np.linalg.inv(normal)
    return cov @ (A.T @ (W * b)), np.sqrt(np.diag(cov))
