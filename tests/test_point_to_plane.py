"""Point-to-plane ICP: accuracy, quality measures and the covariance of degenerate scenes."""

from __future__ import annotations

import numpy as np

from common.geometry import transform_points
from common.point_to_plane import _exp_se3, point_to_plane_hessian, point_to_plane_icp


def plane(rng, n: int, axis: int, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    points = rng.uniform(-1.0, 1.0, (n, 3))
    points[:, axis] = offset
    normals = np.zeros((n, 3))
    normals[:, axis] = 1.0
    return points, normals


def test_icp_recovers_a_motion_between_three_planes():
    rng = np.random.default_rng(0)
    parts = [plane(rng, 2000, axis) for axis in range(3)]
    reference = np.vstack([p for p, _ in parts])
    normals = np.vstack([n for _, n in parts])
    T_true = _exp_se3(np.array([0.03, -0.02, 0.05, 0.04, -0.03, 0.02]))
    query = transform_points(np.linalg.inv(T_true), reference) + rng.normal(0, 0.002, (6000, 3))
    result = point_to_plane_icp(reference, normals, query, np.eye(4))
    assert result.converged
    assert np.abs(result.T_ref_query - T_true).max() < 1e-3
    assert result.inlier_fraction > 0.95 and result.rmse_m < 0.003
    assert result.normalized_min_eigenvalue(1.0) > 0.05


def test_single_plane_covariance_is_large_along_the_unconstrained_directions():
    """z = 0 constrains tz, rx and ry; tx, ty and rz are free, and the covariance says so."""
    rng = np.random.default_rng(1)
    reference, normals = plane(rng, 3000, axis=2)
    query = reference + rng.normal(0, 0.003, reference.shape)
    assert (
        point_to_plane_icp(reference, normals, query, np.eye(4)).normalized_min_eigenvalue(1.0)
        < 1e-6
    )
    # The cost at the true pose (identity), so that the tangent axes are the plane's axes.
    result = point_to_plane_hessian(reference, normals, query, np.eye(4), max_distance_m=0.05)
    sigma = np.sqrt(np.diag(result.covariance()))  # [rx, ry, rz, tx, ty, tz]
    constrained = sigma[[0, 1, 5]]
    free = sigma[[2, 3, 4]]
    assert constrained.max() < 1e-3
    assert free.min() > 100 * constrained.max()
