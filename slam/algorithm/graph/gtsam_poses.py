"""4x4 poses and their covariances in GTSAM's conventions (tangent order ``[rot, trans]``, right
perturbation), for every graph of the package: the live pose graph, its gravity factors, the
loop gates and the merge."""

from __future__ import annotations

import gtsam
import numpy as np

from common.geometry import orthonormalize


def pose3(T: np.ndarray) -> gtsam.Pose3:
    """A 4x4 pose as a ``gtsam.Pose3`` (its rotation re-orthonormalised first)."""
    return gtsam.Pose3(orthonormalize(T))


def relative_pose_covariance(
    joint_covariance: np.ndarray, T_W_Ai: np.ndarray, T_W_Aj: np.ndarray
) -> np.ndarray:
    """6x6 covariance of ``T_Ai_Aj = inv(T_W_Ai) @ T_W_Aj`` from the 12x12 joint marginal of the
    two poses."""
    T_Ai_Aj = pose3(np.linalg.inv(T_W_Ai) @ T_W_Aj)
    A = np.hstack([-T_Ai_Aj.inverse().AdjointMap(), np.eye(6)])
    covariance = A @ joint_covariance @ A.T
    return 0.5 * (covariance + covariance.T)


def mahalanobis_distance2(
    T_graph: np.ndarray,
    covariance_graph: np.ndarray,
    T_registered: np.ndarray,
    covariance_registered: np.ndarray | None,
) -> float:
    """Squared Mahalanobis distance of ``T_registered`` from ``T_graph`` (both ``T_Ai_Aj``),
    with the sum of the two covariances."""
    error = gtsam.Pose3.Logmap(pose3(T_graph).between(pose3(T_registered)))
    covariance = np.asarray(covariance_graph, dtype=np.float64).copy()
    if covariance_registered is not None:
        covariance = covariance + covariance_registered
    return float(error @ np.linalg.solve(covariance, error))
