"""Rigid transforms as 4x4 float64 ``T_a_b`` (frame b to frame a) and rotations as 3x3 matrices.

Exponential and logarithm of SO(3) come from :class:`scipy.spatial.transform.Rotation`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """``(N, 3)`` points from frame b to frame a (float64, a new array)."""
    points_a = np.asarray(points_b) @ np.asarray(T_a_b)[:3, :3].T
    for axis in range(3):  # column by column: broadcasting over rows of 3 is ~5x slower
        points_a[:, axis] += T_a_b[axis, 3]
    return points_a


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """A copy of the 4x4 ``T`` with its rotation replaced by the nearest one in SO(3) (SVD) and its
    last row set to ``0 0 0 1``.

    Poses read from text files are orthogonal only to ~1e-8 (KinectFusion's to ~1e-4), which
    Sophus-based libraries such as KISS-ICP and GTSAM's ``Pose3`` reject.
    """
    T = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    if np.linalg.det(U @ Vt) < 0:  # nearest rotation, not a reflection
        U[:, -1] *= -1
    T[:3, :3] = U @ Vt
    T[3] = [0.0, 0.0, 0.0, 1.0]
    return T


def rotation_angle_rad(R: np.ndarray) -> np.ndarray | float:
    """Angle in radians of a rotation matrix ``(3, 3)`` (a float) or of a stack ``(..., 3, 3)``."""
    R = np.asarray(R, dtype=np.float64)
    cos = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    return float(angle) if angle.ndim == 0 else angle


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` (or ``(N, 3, 3)``) of a rotation vector (axis times angle)."""
    return Rotation.from_rotvec(rotvec).as_matrix()


def relative_motion(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of ``inv(T_a) @ T_b``."""
    D = np.linalg.inv(T_a) @ T_b
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(rotation_angle_rad(D[:3, :3])))
