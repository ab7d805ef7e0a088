"""Rigid poses as float64 4x4 matrices (``T_a_b`` maps points in frame b into frame a).

Quaternions are ``x y z w`` (w last) everywhere in standgrid, as in the pose graphs; the PCD
VIEWPOINT's ``w x y z`` order is converted where it is read.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Matrix4 = NDArray[np.float64]


def pose_matrix(translation: ArrayLike, quat_xyzw: ArrayLike) -> Matrix4:
    """Build ``(..., 4, 4)`` poses from translations ``(..., 3)`` and quaternions ``(..., 4)``.

    Quaternions are normalised; a zero quaternion raises ``ValueError``.
    """
    from scipy.spatial.transform import Rotation

    t = np.asarray(translation, dtype=np.float64)
    q = np.asarray(quat_xyzw, dtype=np.float64)
    batch = t.shape[:-1]
    rot = Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(*batch, 3, 3)
    out = np.zeros((*batch, 4, 4), dtype=np.float64)
    out[..., :3, :3] = rot
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def translation_quat(pose: Matrix4) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Split ``(..., 4, 4)`` poses into translations ``(..., 3)`` and xyzw quaternions."""
    from scipy.spatial.transform import Rotation

    p = np.asarray(pose, dtype=np.float64)
    batch = p.shape[:-2]
    q = Rotation.from_matrix(p[..., :3, :3].reshape(-1, 3, 3)).as_quat().reshape(*batch, 4)
    return p[..., :3, 3].copy(), q


def invert_pose(pose: Matrix4) -> Matrix4:
    """Inverse of rigid poses ``(..., 4, 4)`` (exact: uses R^T)."""
    p = np.asarray(pose, dtype=np.float64)
    out = np.zeros_like(p)
    rt = np.swapaxes(p[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, p[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def relative_pose(pose_i: Matrix4, pose_j: Matrix4) -> Matrix4:
    """``T_i^-1 * T_j``: the pose-graph edge measurement between two vertices."""
    return invert_pose(pose_i) @ np.asarray(pose_j, dtype=np.float64)


def transform_points(pose: Matrix4, xyz: ArrayLike) -> NDArray[np.float64]:
    """Apply one 4x4 pose to points ``(N, 3)``; float64 in, float64 out."""
    p = np.asarray(pose, dtype=np.float64)
    pts = np.asarray(xyz, dtype=np.float64)
    return pts @ p[:3, :3].T + p[:3, 3]


def yaw_of(pose: Matrix4) -> NDArray[np.float64]:
    """Heading (rotation about +z, radians) of poses ``(..., 4, 4)``."""
    p = np.asarray(pose, dtype=np.float64)
    return np.arctan2(p[..., 1, 0], p[..., 0, 0])
