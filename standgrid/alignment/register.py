"""Register one mission's landmarks onto another's, both placed in the catalog CRS.

1. **Coarse, stems**: every pair of a moving and a fixed stem within ``search_radius`` of
   each other (and of a like DBH) votes for the translation between them; votes are summed
   on a ``VOTE_CELL_M`` grid over a 3 x 3 window. The best peak must gather at least
   ``min_stems`` stems and stand clear of the next peak more than 1 m away (a repetitive
   plantation gives several peaks alike: *ambiguous*).
2. **Stems, refined**: stems matched to their nearest fixed stem within a shrinking
   tolerance (0.5, 0.3, 0.15, 0.1 m) give a weighted 2-D Procrustes (yaw and x/y).
3. **Fine, small_gicp**: GICP of the kept ground and stem-band points (never the crowns),
   started from step 2; kept when it stays within ``GICP_AGREE_M`` of the stem solution
   (else the stem solution, with the reason). Its z is the vertical offset; without it the
   median height difference of shared ground cells.

The covariance comes from the matched stems' residuals (a floor of ``MIN_STEM_SIGMA_M``
per stem), doubled for what a rigid model leaves out (SLAM drift within a mission).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]

VOTE_CELL_M = 0.25
#: Headings searched about the GNSS one (degrees): a canopy walk turns a mission ~1 deg.
YAW_SEARCH_DEG = 3.0
YAW_STEP_DEG = 0.5
#: A rival peak counts further than this from the best one (m): a plantation's spacing.
RIVAL_M = 1.5
#: Tolerances (m) of the refining rounds of stem matching.
MATCH_TOLERANCES_M = (0.5, 0.3, 0.15, 0.1)
MIN_STEM_SIGMA_M = 0.02
#: Per-axis floor (m) of a registration's translation: stems of one mission are not
#: independent (ground heights under leaning stems, SLAM drift within the mission).
REGISTRATION_FLOOR_M = 0.02
#: GICP must agree with the stems within this (m, horizontally) to be kept.
GICP_AGREE_M = 0.15
#: Factor on the stem covariance for a rigid model of a mission that drifts a little.
MODEL_FACTOR = 2.0


@dataclass(frozen=True)
class RegisterOptions:
    """How far and how hard to search (see the module doc)."""

    #: Largest horizontal offset searched between two GNSS placements (m).
    search_radius: float = 8.0
    #: Stems a registration needs (matched within the last tolerance).
    min_stems: int = 8
    #: The second peak must gather less than this share of the best one's votes.
    max_peak_ratio: float = 0.7
    #: Run small_gicp's GICP after the stems (False: the stems alone).
    gicp: bool = True
    gicp_threads: int = 1


@dataclass(frozen=True)
class Registration:
    """``moving`` -> ``fixed`` in the catalog CRS: ``p_fixed = R(yaw) (p - pivot) + pivot + t``
    horizontally and ``z + dz``. ``covariance``: of (tx, ty, yaw) about ``pivot``.
    ``accepted`` False: ``reason`` says why (the numbers are then not to be used)."""

    moving: str
    fixed: str
    accepted: bool
    reason: str = ""
    pivot: tuple[float, float] = (0.0, 0.0)
    t: tuple[float, float] = (0.0, 0.0)
    yaw: float = 0.0
    dz: float = 0.0
    covariance: tuple[tuple[float, ...], ...] = ()
    sigma_z: float = math.nan
    stems_matched: int = 0
    rms_m: float = math.nan
    peak_ratio: float = math.nan
    gicp: str = ""
    details: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        out = {
            "moving": self.moving,
            "fixed": self.fixed,
            "accepted": self.accepted,
            "reason": self.reason,
        }
        if self.accepted:
            out.update(
                t_m=[round(v, 4) for v in self.t],
                yaw_deg=round(math.degrees(self.yaw), 5),
                dz_m=round(self.dz, 4),
                pivot=list(self.pivot),
                sigma_m=round(math.sqrt(self.covariance[0][0] + self.covariance[1][1]), 4),
                sigma_yaw_deg=round(math.degrees(math.sqrt(self.covariance[2][2])), 5),
                sigma_z_m=round(self.sigma_z, 4),
                stems_matched=self.stems_matched,
                rms_m=round(self.rms_m, 4),
                peak_ratio=round(self.peak_ratio, 3),
                gicp=self.gicp,
            )
        else:
            out.update(stems_matched=self.stems_matched)
        return out


def rot2d(yaw: float) -> FloatArray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


def _procrustes(a: FloatArray, b: FloatArray) -> tuple[FloatArray, float, FloatArray]:
    """Yaw and translation taking ``a`` onto ``b`` (2-D): ``b = R (a - ca) + cb``."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, v = a - ca, b - cb
    yaw = math.atan2(
        float(np.sum(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])),
        float(np.sum(u[:, 0] * v[:, 0] + u[:, 1] * v[:, 1])),
    )
    return ca, yaw, cb


def _votes(
    moving: FloatArray, fixed: FloatArray, radius: float
) -> tuple[FloatArray, float, float] | None:
    """The best voted translation, its smoothed votes and the best rival's (further than
    ``RIVAL_M``)."""
    tree = cKDTree(fixed[:, :2])
    near = tree.query_ball_point(moving[:, :2], radius)
    rows = np.repeat(np.arange(len(moving)), [len(n) for n in near])
    cols = np.fromiter((j for n in near for j in n), np.int64, len(rows))
    if not len(rows):
        return None
    dbh_m, dbh_f = moving[rows, 3], fixed[cols, 3]
    like = np.abs(dbh_m - dbh_f) <= 0.3 * np.maximum(dbh_m, dbh_f) + 0.03
    rows, cols = rows[like], cols[like]
    if not len(rows):
        return None
    d = fixed[cols, :2] - moving[rows, :2]
    n = math.ceil(radius / VOTE_CELL_M)
    ij = np.clip(np.floor(d / VOTE_CELL_M).astype(np.int64) + n, 0, 2 * n - 1)
    grid = np.zeros((2 * n, 2 * n))
    np.add.at(grid, (ij[:, 0], ij[:, 1]), 1.0)
    from scipy import ndimage

    smooth = ndimage.uniform_filter(grid, size=3, mode="constant") * 9.0
    best = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
    peak = float(smooth[best])
    # the best rival: the highest cell further than RIVAL_M from the peak
    xx, yy = np.meshgrid(np.arange(2 * n), np.arange(2 * n), indexing="ij")
    far = np.hypot(xx - best[0], yy - best[1]) * VOTE_CELL_M > RIVAL_M
    rival = float(smooth[far].max()) if far.any() else 0.0
    # the translation: the mean of the votes around the peak
    around = (np.abs(ij[:, 0] - best[0]) <= 1) & (np.abs(ij[:, 1] - best[1]) <= 1)
    return d[around].mean(axis=0), peak, rival


def _match(
    moving: FloatArray, tree: cKDTree, tolerance: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Mutual nearest pairs within ``tolerance`` (moving rows, fixed rows)."""
    dist, j = tree.query(moving, distance_upper_bound=tolerance)
    ok = np.isfinite(dist)
    rows, cols = np.flatnonzero(ok), j[ok]
    # one fixed stem takes one moving stem: the nearest
    order = np.lexsort((dist[ok], cols))
    first = np.r_[True, cols[order][1:] != cols[order][:-1]]
    return rows[order][first], cols[order][first]


def register(
    moving: Any,
    fixed: Any,
    options: RegisterOptions = RegisterOptions(),
) -> Registration:
    """Register ``moving`` onto ``fixed`` (both :class:`PlacedLandmarks`, in the CRS)."""
    ms, fs = moving.stems, fixed.stems
    name, other = moving.name, fixed.name
    if len(ms) < options.min_stems or len(fs) < options.min_stems:
        return Registration(
            name,
            other,
            False,
            f"too few stems: {len(ms)} and {len(fs)} (at least {options.min_stems} each)",
        )
    pivot = ms[:, :2].mean(axis=0)
    best: tuple[float, FloatArray, float, float] | None = None
    for yaw_deg in np.arange(-YAW_SEARCH_DEG, YAW_SEARCH_DEG + 1e-9, YAW_STEP_DEG):
        turned = ms.copy()
        turned[:, :2] = (ms[:, :2] - pivot) @ rot2d(math.radians(yaw_deg)).T + pivot
        voted = _votes(turned, fs, options.search_radius)
        if voted is not None and (best is None or voted[1] > best[2]):
            best = (math.radians(yaw_deg), *voted)
    if best is None:
        return Registration(name, other, False, "no overlap: no stems within reach")
    yaw, shift, peak, rival = best
    ratio = rival / peak if peak > 0 else math.inf
    if peak < options.min_stems:
        return Registration(
            name,
            other,
            False,
            f"too little overlap: {peak:.0f} stems agree (at least {options.min_stems})",
            peak_ratio=ratio,
        )
    if ratio >= options.max_peak_ratio:
        return Registration(
            name,
            other,
            False,
            f"ambiguous: a second offset gathers {ratio:.0%} of the best one's "
            "stems (a repetitive stand?)",
            peak_ratio=ratio,
        )
    tree = cKDTree(fs[:, :2])
    t = np.asarray(shift, dtype=np.float64)
    rows = cols = np.zeros(0, dtype=np.int64)
    for tolerance in MATCH_TOLERANCES_M:
        moved = (ms[:, :2] - pivot) @ rot2d(yaw).T + pivot + t
        rows, cols = _match(moved, tree, tolerance)
        if len(rows) < max(3, options.min_stems // 2):
            return Registration(
                name,
                other,
                False,
                f"does not converge: {len(rows)} stems within {tolerance} m",
                stems_matched=len(rows),
                peak_ratio=ratio,
            )
        ca, yaw, cb = _procrustes(ms[rows, :2], fs[cols, :2])
        # b = R (a - ca) + cb  ==  R (a - pivot) + pivot + t
        t = cb - pivot - rot2d(yaw) @ (ca - pivot)
    if len(rows) < options.min_stems:
        return Registration(
            name,
            other,
            False,
            f"too little overlap: {len(rows)} stems matched within "
            f"{MATCH_TOLERANCES_M[-1]} m (at least {options.min_stems})",
            stems_matched=len(rows),
            peak_ratio=ratio,
        )
    moved = (ms[rows, :2] - pivot) @ rot2d(yaw).T + pivot + t
    resid = moved - fs[cols, :2]
    rms = float(np.sqrt(np.mean(np.sum(resid**2, axis=1)) / 2.0))  # per axis
    dz_stems = float(np.median(fs[cols, 2] - ms[rows, 2]))
    gicp_note, dz = "", dz_stems
    if options.gicp:
        result = _gicp(moving, fixed, pivot, yaw, t, dz_stems, options)
        if isinstance(result, str):
            gicp_note = result
        else:
            g_yaw, g_t, g_dz = result
            g_moved = (ms[rows, :2] - pivot) @ rot2d(g_yaw).T + pivot + g_t
            shift_m = float(np.max(np.hypot(*(g_moved - moved).T)))
            if shift_m <= GICP_AGREE_M:
                yaw, t, dz, gicp_note = g_yaw, g_t, g_dz, f"kept (moved the stems {shift_m:.3f} m)"
                moved = g_moved
                resid = moved - fs[cols, :2]
                rms = float(np.sqrt(np.mean(np.sum(resid**2, axis=1)) / 2.0))
            else:
                gicp_note = f"left out: {shift_m:.2f} m from the stems' solution"
    sigma = max(rms, MIN_STEM_SIGMA_M) * MODEL_FACTOR
    n = len(rows)
    spread = float(np.sum((ms[rows, :2] - ms[rows, :2].mean(axis=0)) ** 2))
    offset = ms[rows, :2].mean(axis=0) - pivot  # the matched stems' centre from the pivot
    # (t, yaw) about the pivot: translation of the centre sigma^2 / n, yaw sigma^2 / spread
    var_yaw = sigma**2 / max(spread, 1e-6)
    lever = np.array([-offset[1], offset[0]])
    cov = np.zeros((3, 3))
    var_t = max(sigma**2 / n, REGISTRATION_FLOOR_M**2)
    cov[:2, :2] = np.eye(2) * var_t + np.outer(lever, lever) * var_yaw
    cov[:2, 2] = cov[2, :2] = -lever * var_yaw
    cov[2, 2] = var_yaw
    dz_spread = np.abs(fs[cols, 2] - ms[rows, 2] - dz)
    sigma_z = max(float(np.median(dz_spread)) * 1.4826 / math.sqrt(n), 0.01) * MODEL_FACTOR
    return Registration(
        name,
        other,
        True,
        "",
        (float(pivot[0]), float(pivot[1])),
        (float(t[0]), float(t[1])),
        float(yaw),
        float(dz),
        tuple(tuple(float(v) for v in row) for row in cov),
        sigma_z,
        n,
        rms,
        ratio,
        gicp_note,
    )


def _gicp(
    moving: Any,
    fixed: Any,
    pivot: FloatArray,
    yaw: float,
    t: FloatArray,
    dz: float,
    options: RegisterOptions,
) -> tuple[float, FloatArray, float] | str:
    """small_gicp's GICP of the kept points, started from the stems' solution."""
    try:
        import small_gicp
    except ImportError:  # pragma: no cover - a declared dependency
        return "left out: small_gicp is not installed"
    # the overlap only, about the pivot (small numbers for the solver)
    mp, fp = moving.points, fixed.points
    lo = np.maximum(mp[:, :2].min(axis=0), fp[:, :2].min(axis=0)) - 2.0
    hi = np.minimum(mp[:, :2].max(axis=0), fp[:, :2].max(axis=0)) + 2.0
    centre = np.array([pivot[0], pivot[1], float(np.median(fp[:, 2]))])

    def inside(p: FloatArray) -> FloatArray:
        keep = np.all((p[:, :2] >= lo) & (p[:, :2] <= hi), axis=1)
        return p[keep] - centre

    src, dst = inside(mp), inside(fp)
    if len(src) < 1000 or len(dst) < 1000:
        return "left out: too few points in the overlap"
    init = np.eye(4)
    init[:2, :2] = rot2d(yaw)
    init[:2, 3] = t
    init[2, 3] = dz
    try:
        result = small_gicp.align(
            dst,
            src,
            init_T_target_source=init,
            registration_type="GICP",
            downsampling_resolution=0.05,
            max_correspondence_distance=0.3,
            num_threads=options.gicp_threads,
            max_iterations=30,
        )
    except Exception as exc:
        return f"left out: small_gicp failed ({exc})"
    if not result.converged:
        return "left out: GICP did not converge"
    T = np.asarray(result.T_target_source)
    g_yaw = math.atan2(T[1, 0], T[0, 0])
    return g_yaw, T[:2, 3].copy(), float(T[2, 3])


#: Global search: stem pairs this far apart (m) make the hypotheses; lengths agree within
#: ``PAIR_TOLERANCE_M``; votes are binned by ``GLOBAL_YAW_STEP_DEG`` and ``GLOBAL_CELL_M``.
PAIR_RANGE_M = (4.0, 15.0)
PAIR_TOLERANCE_M = 0.05
GLOBAL_YAW_STEP_DEG = 2.0
GLOBAL_CELL_M = 1.0
#: The stoutest stems of each side used by the global search (its cost grows as n^2).
GLOBAL_STEMS = 150
#: The global search looks this far (m) beyond the mission's extent around where its
#: metadata puts it.
GLOBAL_REACH_M = 150.0


def _pairs(stems: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatArray]:
    tree = cKDTree(stems[:, :2])
    pairs = tree.query_pairs(PAIR_RANGE_M[1], output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    length = np.hypot(*(stems[j, :2] - stems[i, :2]).T)
    keep = length >= PAIR_RANGE_M[0]
    return i[keep], j[keep], length[keep]


def _stoutest(stems: FloatArray) -> FloatArray:
    return stems[np.argsort(-stems[:, 3], kind="stable")[:GLOBAL_STEMS]]


def global_guess(
    moving: FloatArray, fixed: FloatArray, about: FloatArray
) -> tuple[float, FloatArray, float, float] | None:
    """Yaw (about the point ``about``) and translation that put the moving stems on the
    fixed ones, from any start: every pair of moving stems matched to fixed pairs of the
    same length and like DBHs votes for the rotation and shift between them. Returns
    ``(yaw, t, votes, best rival's votes)`` or None."""
    ms, fs = _stoutest(moving), _stoutest(fixed)
    if len(ms) < 3 or len(fs) < 3:
        return None
    mi, mj, ml = _pairs(ms)
    fi, fj, fl = _pairs(fs)
    if not len(ml) or not len(fl):
        return None
    # both directions of each fixed pair
    fi, fj, fl = np.r_[fi, fj], np.r_[fj, fi], np.r_[fl, fl]
    order = np.argsort(fl)
    fi, fj, fl = fi[order], fj[order], fl[order]
    lo = np.searchsorted(fl, ml - PAIR_TOLERANCE_M)
    hi = np.searchsorted(fl, ml + PAIR_TOLERANCE_M)
    count = hi - lo
    a = np.repeat(np.arange(len(ml)), count)
    b = (
        np.concatenate([np.arange(s, e) for s, e in zip(lo, hi, strict=True)])
        if len(a)
        else np.zeros(0, dtype=np.int64)
    )
    if not len(a):
        return None
    like = (
        np.abs(ms[mi[a], 3] - fs[fi[b], 3]) <= 0.3 * np.maximum(ms[mi[a], 3], fs[fi[b], 3]) + 0.03
    ) & (np.abs(ms[mj[a], 3] - fs[fj[b], 3]) <= 0.3 * np.maximum(ms[mj[a], 3], fs[fj[b], 3]) + 0.03)
    a, b = a[like], b[like]
    if not len(a):
        return None
    vm = ms[mj[a], :2] - ms[mi[a], :2]
    vf = fs[fj[b], :2] - fs[fi[b], :2]
    yaw = np.arctan2(vf[:, 1], vf[:, 0]) - np.arctan2(vm[:, 1], vm[:, 0])
    centre = ms[:, :2].mean(axis=0)
    c, s = np.cos(yaw), np.sin(yaw)
    p = ms[mi[a], :2] - centre
    turned = np.column_stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]]) + centre
    shift = fs[fi[b], :2] - turned
    yk = np.floor(np.mod(np.degrees(yaw), 360.0) / GLOBAL_YAW_STEP_DEG).astype(np.int64)
    xk = np.floor(shift / GLOBAL_CELL_M).astype(np.int64)
    keys = np.column_stack([yk, xk])
    bins, inverse, votes = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    best = int(np.argmax(votes))
    inverse = inverse.ravel()
    chosen = inverse == best
    mean_yaw = math.atan2(float(np.mean(s[chosen])), float(np.mean(c[chosen])))
    # a rival: the best bin more than a yaw bin (wrapping) or two shift cells away
    turns = round(360.0 / GLOBAL_YAW_STEP_DEG)
    dyaw = np.abs(bins[:, 0] - bins[best, 0])
    dyaw = np.minimum(dyaw, turns - dyaw)
    far = (dyaw > 1) | (np.abs(bins[:, 1:] - bins[best, 1:]).max(axis=1) > 2)
    rival = float(votes[far].max()) if far.any() else 0.0
    # the shift for that yaw (the votes' mean) about the stout stems' centre, moved to one
    # about ``about`` (the centre the caller turns about)
    rot = rot2d(mean_yaw)
    t = shift[chosen].mean(axis=0) + (rot - np.eye(2)) @ (np.asarray(about) - centre)
    return mean_yaw, t, float(votes[best]), rival


def register_global(
    moving: Any, fixed: Any, options: RegisterOptions = RegisterOptions()
) -> Registration:
    """:func:`register` for a mission placed nowhere near right (no GNSS): the global stem
    search first (:func:`global_guess`), then the usual registration from there; the
    result is the composition, about the moving stems' centre."""
    from dataclasses import replace

    ms, fs = moving.stems, fixed.stems
    if len(ms) < options.min_stems or len(fs) < options.min_stems:
        return Registration(
            moving.name,
            fixed.name,
            False,
            f"too few stems: {len(ms)} and {len(fs)} (at least {options.min_stems} each)",
        )
    # the other side's stems near where the metadata put this mission (its extent plus
    # GLOBAL_REACH_M): the stoutest of a large catalog would lie mostly elsewhere
    centre0 = ms[:, :2].mean(axis=0)
    extent = float(np.max(np.hypot(*(ms[:, :2] - centre0).T)))
    near = np.hypot(*(fs[:, :2] - centre0).T) <= extent + GLOBAL_REACH_M
    if near.sum() < options.min_stems:
        return Registration(
            moving.name,
            fixed.name,
            False,
            f"no overlap: {int(near.sum())} stems within "
            f"{GLOBAL_REACH_M:.0f} m of where its metadata puts it",
        )
    centre = ms[:, :2].mean(axis=0)
    guess = global_guess(ms, fs[near], centre)
    if guess is None:
        return Registration(
            moving.name,
            fixed.name,
            False,
            "no stems alike: the global search found no pair of stems",
        )
    yaw0, t0, votes, rival = guess
    if rival >= options.max_peak_ratio * votes:
        return Registration(
            moving.name,
            fixed.name,
            False,
            f"ambiguous: the global search's second placement gathers "
            f"{rival / votes:.0%} of the best one's votes",
            peak_ratio=rival / votes,
        )
    rot0 = rot2d(yaw0)

    def first(p: FloatArray) -> FloatArray:
        out = p.copy()
        out[:, :2] = (p[:, :2] - centre) @ rot0.T + centre + t0
        return out

    start = type(moving)(
        moving.name,
        first(ms),
        first(moving.points) if len(moving.points) else moving.points,
        first(moving.nodes),
    )
    fine = register(start, fixed, replace(options, search_radius=3.0))
    if not fine.accepted:
        return replace(fine, reason=f"global search ({votes:.0f} votes) then {fine.reason}")
    # compose: p -> R1 (R0 (p - c) + c + t0 - pv) + pv + t1, about c: R1 R0 (p - c) + c + t
    pv = np.asarray(fine.pivot)
    rot1 = rot2d(fine.yaw)
    t = rot1 @ (centre + t0 - pv) + pv + np.asarray(fine.t) - centre
    yaw = math.atan2(math.sin(yaw0 + fine.yaw), math.cos(yaw0 + fine.yaw))
    # the covariance of (t about c, yaw): the fine one moved from its pivot to c
    lever = centre + t0 - pv  # where c went, from the pivot, before the fine turn
    j = np.eye(3)
    j[:2, 2] = np.array([[0.0, -1.0], [1.0, 0.0]]) @ rot1 @ lever
    cov = j @ np.asarray(fine.covariance) @ j.T
    return replace(
        fine,
        pivot=(float(centre[0]), float(centre[1])),
        t=(float(t[0]), float(t[1])),
        yaw=yaw,
        covariance=tuple(tuple(float(v) for v in row) for row in cov),
        details={**fine.details, "global_votes": votes},
    )
