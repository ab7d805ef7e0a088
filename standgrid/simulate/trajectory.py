"""Robot trajectories through a stand: waypoint patterns, nodes, true and estimated poses."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from standgrid.geometry import Matrix4, relative_pose

Bounds = tuple[float, float, float, float]


def serpentine_waypoints(
    rng: np.random.Generator,
    bounds: Bounds,
    *,
    along: str = "y",
    inset: float = 10.0,
    max_line_spacing: float = 32.0,
) -> NDArray[np.float64]:
    """Parallel lines (lawnmower) along ``along``, then one line across them back towards the start.

    The crossing line revisits every lane, which gives the graph its loop closures.
    """
    xmin, ymin, xmax, ymax = bounds
    if along == "x":  # swap the roles of the axes, build, swap back
        swapped = serpentine_waypoints(
            rng, (ymin, xmin, ymax, xmax), along="y", inset=inset, max_line_spacing=max_line_spacing
        )
        return swapped[:, ::-1].copy()
    lo, hi = xmin + inset, xmax - inset
    n_lines = max(2, int(np.ceil((hi - lo) / max_line_spacing)) + 1)
    lanes = np.linspace(lo, hi, n_lines) + rng.uniform(-1.5, 1.5, n_lines)
    y0, y1 = ymin + inset, ymax - inset
    pts: list[tuple[float, float]] = []
    for k, x in enumerate(lanes):
        ends = (y0, y1) if k % 2 == 0 else (y1, y0)
        pts += [(x, ends[0]), (x, ends[1])]
    y_mid = (y0 + y1) / 2 + rng.uniform(-5.0, 5.0)
    last_x = lanes[-1]
    pts += [(last_x, y_mid), (lanes[0] - 0.0, y_mid)]
    return np.asarray(pts, dtype=np.float64)


def clip_waypoints(
    waypoints: NDArray[np.float64], outline: list[tuple[float, float]]
) -> NDArray[np.float64]:
    """The parts of a waypoint path inside a polygon, joined in order (a robot walking
    only the survey area: each leg keeps its longest piece inside)."""
    import shapely

    polygon = shapely.Polygon(outline)
    pts: list[tuple[float, float]] = []
    for a, b in itertools.pairwise(waypoints):
        inside = shapely.LineString([a, b]).intersection(polygon)
        pieces = list(getattr(inside, "geoms", [inside]))
        pieces = [p for p in pieces if isinstance(p, shapely.LineString) and not p.is_empty]
        if not pieces:
            continue
        longest = max(pieces, key=lambda p: p.length)
        pts.extend((float(x), float(y)) for x, y in longest.coords)
    if len(pts) < 2:
        raise ValueError("the survey polygon holds no part of the robot's path")
    return np.asarray(pts, dtype=np.float64)


def resample_polyline(
    waypoints: NDArray[np.float64], spacing: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Points every ``spacing`` metres along a 2-D polyline, and their arc lengths."""
    seg = np.diff(waypoints, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    keep = seg_len > 1e-9
    wp = np.vstack([waypoints[:1], waypoints[1:][keep]])
    cum = np.concatenate([[0.0], np.cumsum(seg_len[keep])])
    s = np.arange(0.0, cum[-1] + 1e-9, spacing)
    xy = np.column_stack([np.interp(s, cum, wp[:, 0]), np.interp(s, cum, wp[:, 1])])
    return xy, s


def poses_from_positions(
    rng: np.random.Generator,
    positions: NDArray[np.float64],
    *,
    tilt_std_deg: float = 1.5,
) -> Matrix4:
    """``T_map_base`` per node: heading along the path, small smooth roll and pitch."""
    n = len(positions)
    fwd = np.gradient(positions[:, :2], axis=0) if n > 1 else np.array([[1.0, 0.0]])
    yaw = np.arctan2(fwd[:, 1], fwd[:, 0])
    kernel = np.ones(7) / 7.0
    roll = np.convolve(rng.normal(0, tilt_std_deg * 2.0, n), kernel, mode="same")
    pitch = np.convolve(rng.normal(0, tilt_std_deg * 2.0, n), kernel, mode="same")
    rot = Rotation.from_euler("ZYX", np.column_stack([yaw, np.radians(pitch), np.radians(roll)]))
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :3] = rot.as_matrix()
    poses[:, :3, 3] = positions
    poses[:, 3, 3] = 1.0
    return poses


def drifted_poses(rng: np.random.Generator, true_poses: Matrix4, drift_m: float = 0.03) -> Matrix4:
    """A SLAM-like estimate: true poses plus a slow random-walk drift reaching ~``drift_m``."""
    n = len(true_poses)
    if drift_m <= 0 or n < 2:
        return true_poses.copy()
    step = drift_m / np.sqrt(n)
    d_xyz = np.cumsum(rng.normal(0.0, step, (n, 3)), axis=0)
    d_xyz[:, 2] *= 0.5
    d_yaw = np.cumsum(rng.normal(0.0, drift_m / 20.0 / np.sqrt(n), n))
    est = true_poses.copy()
    est[:, :3, 3] += d_xyz
    est[:, :3, :3] = Rotation.from_euler("z", d_yaw[:, None]).as_matrix() @ true_poses[:, :3, :3]
    return est


def loop_closure_pairs(
    positions: NDArray[np.float64], *, radius: float = 2.5, min_gap: int = 40, stride: int = 6
) -> list[tuple[int, int]]:
    """Node pairs ``(i, j)`` revisiting a place: ``j - i >= min_gap``, closer than ``radius``."""
    tree = cKDTree(positions[:, :2])
    pairs: list[tuple[int, int]] = []
    last_j_for_i = -(10**9)
    for i in range(len(positions)):
        candidates = [
            j for j in tree.query_ball_point(positions[i, :2], radius) if j - i >= min_gap
        ]
        if not candidates or i - last_j_for_i < stride:
            continue
        j = min(candidates, key=lambda c: float(np.linalg.norm(positions[c] - positions[i])))
        pairs.append((i, j))
        last_j_for_i = i
    return pairs


def noisy_relative(
    rng: np.random.Generator, pose_i: Matrix4, pose_j: Matrix4, t_std: float, r_std: float
) -> Matrix4:
    """A relative-pose measurement ``T_i^-1 T_j`` with small Gaussian noise."""
    rel = relative_pose(pose_i, pose_j)
    noise = np.eye(4)
    noise[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, r_std, 3)).as_matrix()
    noise[:3, 3] = rng.normal(0.0, t_std, 3)
    return rel @ noise


def information_matrix(t_std: float, r_std: float) -> NDArray[np.float64]:
    """Diagonal 6x6 information (translation block first)."""
    return np.diag([1.0 / t_std**2] * 3 + [1.0 / r_std**2] * 3)


@dataclass(frozen=True)
class Span:
    """One payload: nodes ``[first, last]`` travelled while it was recorded, owned by ``centre``."""

    first: int
    last: int
    centre: int


def payload_spans(arc_length: NDArray[np.float64], spacing: float = 20.0) -> list[Span]:
    """Cut the path into ~``spacing`` m spans (a short tail joins the previous span)."""
    total = float(arc_length[-1])
    n_spans = max(1, round(total / spacing))
    edges = np.linspace(0.0, total, n_spans + 1)
    spans = []
    for k in range(n_spans):
        inside = np.flatnonzero((arc_length >= edges[k]) & (arc_length < edges[k + 1]))
        if k == n_spans - 1:
            inside = np.flatnonzero(arc_length >= edges[k])
        mid = (edges[k] + edges[k + 1]) / 2
        centre = int(inside[np.argmin(np.abs(arc_length[inside] - mid))])
        spans.append(Span(int(inside[0]), int(inside[-1]), centre))
    return spans
