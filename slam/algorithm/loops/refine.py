"""The dense refinement's inputs and diagnostics for RGB-D loop closure
(:mod:`slam.algorithm.loops.rgbd`): a thinned cloud with normals and its k-d tree, and the scores
a refinement adds to a loop candidate."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from common.geometry import relative_motion
from common.point_to_plane import IcpResult
from slam.algorithm.voxel_grid import voxel_downsample


@dataclass
class RefineCloud:
    """A thinned cloud with unit normals in the keyframe (anchor) frame, and its k-d tree."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree
    radius_m: float
    spacing_m: float = 0.0

    @classmethod
    def build(
        cls, points: np.ndarray, normals: np.ndarray | None, voxel_m: float, max_points: int
    ) -> RefineCloud | None:
        if normals is None or len(points) == 0:
            return None
        points = np.asarray(points, dtype=np.float64)
        normals = np.asarray(normals, dtype=np.float64)
        good = np.isfinite(points).all(axis=1) & (np.linalg.norm(normals, axis=1) > 0.5)
        points, normals = voxel_downsample(voxel_m, points[good], normals[good])
        length = np.linalg.norm(normals, axis=1)
        keep = length > 0.5
        points, normals = points[keep], normals[keep] / length[keep, None]
        if len(points) > max_points:
            pick = np.random.default_rng(0).choice(len(points), max_points, replace=False)
            points, normals = points[np.sort(pick)], normals[np.sort(pick)]
        if len(points) < 100:
            return None
        radius = float(np.sqrt(np.mean(np.sum((points - points.mean(0)) ** 2, axis=1))))
        tree = cKDTree(points)
        spacing = float(np.median(tree.query(points, k=2)[0][:, 1]))
        return cls(points, normals, tree, radius, spacing)


def refine_scores(result: IcpResult, T_guess: np.ndarray, radius_m: float) -> dict[str, float]:
    """Diagnostics of a dense refinement for the loop candidate's scores."""
    correction_m, correction_deg = relative_motion(T_guess, result.T_ref_query)
    return {
        "dense_inlier_fraction": result.inlier_fraction,
        "dense_rmse_m": result.rmse_m,
        "dense_residual_sigma_m": result.robust_sigma_m,
        "dense_correction_m": correction_m,
        "dense_correction_deg": correction_deg,
        "dense_min_eigenvalue": result.normalized_min_eigenvalue(radius_m),
        "dense_iterations": float(result.iterations),
    }
