"""Point-to-plane ICP with its quality and its information matrix.

Used by the RGB-D odometry (the information of each registration), and by loop closure to
refine loop edges densely (RGB-D: between two submaps' clouds) and to judge any
registration by its cost: the Gauss-Newton Hessian ``H = sum_k J_k^T J_k`` of the point-to-plane
residuals ``r_k = n_k . (T p_k - q_k)`` at the solution says which directions the geometry
constrains. Its smallest eigenvalue is near zero for a degenerate scene (one plane, a straight
corridor); the covariance of the estimate is ``sigma^2 H^-1`` with ``sigma^2`` the residual
variance (the usual least-squares estimate, e.g. Censi 2007 without the correspondence term).

Tangent space: GTSAM's Pose3 order ``[rx, ry, rz, tx, ty, tz]`` with the perturbation applied on
the *right* (``T exp(xi)``), so that the covariance can be used by a ``BetweenFactorPose3``
directly. Internally the solver perturbs on the left (in the reference frame) and converts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from common.geometry import orthonormalize, so3_exp, transform_points


@dataclass
class IcpResult:
    """Outcome of :func:`point_to_plane_icp`.

    Attributes:
        T_ref_query: the estimate (query points to the reference frame).
        converged: the last update was below the tolerance.
        inlier_fraction: query points with a correspondence within the final distance.
        rmse_m: RMS point-to-plane residual of the inliers.
        robust_sigma_m: 1.4826 x the median absolute point-to-plane residual of the inliers (the
            residual spread without the tails of partly overlapping clouds).
        hessian: 6x6 Gauss-Newton Hessian at the solution, right-perturbation ``[rot, trans]``.
        num_inliers: correspondences used in the last iteration.
        iterations: Gauss-Newton iterations run.
    """

    T_ref_query: np.ndarray
    converged: bool
    inlier_fraction: float
    rmse_m: float
    hessian: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    num_inliers: int = 0
    iterations: int = 0
    robust_sigma_m: float = float("inf")

    def normalized_min_eigenvalue(self, length_m: float) -> float:
        """Smallest eigenvalue of the Hessian per inlier, rotation scaled by ``length_m``.

        Unitless, in [0, 1]: about the fraction of correspondences whose normals constrain the
        weakest direction; 0 for a direction the cost does not see at all.
        """
        if self.num_inliers == 0:
            return 0.0
        scale = np.array([length_m] * 3 + [1.0] * 3)
        H = self.hessian / np.outer(scale, scale) / self.num_inliers
        return float(np.linalg.eigvalsh(H)[0])

    def covariance(self, factor: float = 1.0, min_sigma_m: float = 1e-3) -> np.ndarray:
        """``factor * sigma^2 H^-1`` (right-perturbation ``[rot, trans]``).

        ``sigma`` is the residual RMSE, floored at ``min_sigma_m`` (sensor noise that a perfect
        fit on few points would hide). ``factor`` inflates it for what the model ignores:
        correlated residuals of neighbouring points and correspondence errors. Directions the
        Hessian does not constrain get a variance of about ``sigma^2 / 1e-9``.
        """
        sigma2 = max(self.rmse_m, min_sigma_m) ** 2
        H = self.hessian + np.eye(6) * 1e-9
        cov = factor * sigma2 * np.linalg.inv(H)
        return 0.5 * (cov + cov.T)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _exp_se3(xi: np.ndarray) -> np.ndarray:
    """4x4 transform of a twist ``[w, v]`` (small steps: first-order translation is enough)."""
    T = np.eye(4)
    T[:3, :3] = so3_exp(xi[:3])
    T[:3, 3] = xi[3:]
    return T


def adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint of ``T`` for twists ordered ``[w, v]``."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = _skew(t) @ R
    return A


def point_to_plane_icp(
    reference: np.ndarray,
    reference_normals: np.ndarray,
    query: np.ndarray,
    T_ref_query_guess: np.ndarray,
    max_distances_m: tuple[float, ...] = (0.1, 0.05, 0.025),
    max_iterations: int = 15,
    tolerance: float = 1e-5,
    tree: cKDTree | None = None,
) -> IcpResult:
    """Align ``query`` onto ``reference`` (with unit normals) by robust point-to-plane ICP.

    One pass per entry of ``max_distances_m`` (coarse to fine correspondence gates); residuals
    are weighted by a Huber kernel at a third of the gate. ``tree`` may be a prebuilt
    ``cKDTree(reference)``.
    """
    reference = np.asarray(reference, dtype=np.float64)
    normals = np.asarray(reference_normals, dtype=np.float64)
    query = np.asarray(query, dtype=np.float64)
    tree = tree if tree is not None else cKDTree(reference)
    T = orthonormalize(T_ref_query_guess)
    result = IcpResult(T, False, 0.0, float("inf"))
    if len(reference) < 6 or len(query) < 6:
        return result
    iterations = 0
    converged = False
    for gate in max_distances_m:
        converged = False
        for _ in range(max_iterations):
            iterations += 1
            moved = transform_points(T, query)
            distance, index = tree.query(moved, k=1, distance_upper_bound=gate)
            ok = np.isfinite(distance)
            if ok.sum() < 6:
                return IcpResult(T, False, float(ok.mean()), float("inf"), iterations=iterations)
            p, q, n = moved[ok], reference[index[ok]], normals[index[ok]]
            r = np.einsum("ij,ij->i", p - q, n)
            J = np.hstack([np.cross(p, n), n])  # left perturbation [w, v] in the reference frame
            huber = gate / 3.0
            w = np.where(np.abs(r) <= huber, 1.0, huber / np.maximum(np.abs(r), 1e-12))
            H = (J * w[:, None]).T @ J
            g = (J * w[:, None]).T @ r
            try:
                step = -np.linalg.solve(H + np.eye(6) * 1e-9, g)
            except np.linalg.LinAlgError:
                return IcpResult(T, False, 0.0, float("inf"), iterations=iterations)
            T = _exp_se3(step) @ T
            if np.linalg.norm(step) < tolerance:
                converged = True
                break
    moved = transform_points(T, query)
    distance, index = tree.query(moved, k=1, distance_upper_bound=max_distances_m[-1])
    ok = np.isfinite(distance)
    if ok.sum() < 6:
        return IcpResult(T, False, float(ok.mean()), float("inf"), iterations=iterations)
    p, q, n = moved[ok], reference[index[ok]], normals[index[ok]]
    r = np.einsum("ij,ij->i", p - q, n)
    J_left = np.hstack([np.cross(p, n), n])
    # Right perturbation: T exp(xi) = exp(Ad_T xi) T, so J_right = J_left Ad_T.
    J = J_left @ adjoint(T)
    return IcpResult(
        T_ref_query=T,
        converged=converged,
        inlier_fraction=float(ok.mean()),
        rmse_m=float(np.sqrt(np.mean(r**2))),
        hessian=J.T @ J,
        num_inliers=int(ok.sum()),
        iterations=iterations,
        robust_sigma_m=float(1.4826 * np.median(np.abs(r))),
    )


def point_to_plane_hessian(
    reference: np.ndarray,
    reference_normals: np.ndarray,
    query: np.ndarray,
    T_ref_query: np.ndarray,
    max_distance_m: float,
    tree: cKDTree | None = None,
) -> IcpResult:
    """Quality and Hessian of a given alignment (no iterations): the cost seen at ``T``."""
    return point_to_plane_icp(
        reference,
        reference_normals,
        query,
        T_ref_query,
        max_distances_m=(max_distance_m,),
        max_iterations=0,
        tree=tree,
    )
