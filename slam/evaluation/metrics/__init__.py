"""Evaluation against ground truth: trajectory errors and mesh accuracy/completion."""

from slam.evaluation.metrics.mesh import (
    MeshMetrics,
    mesh_metrics,
    surface_distances,
    visible_face_mask,
)
from slam.evaluation.metrics.trajectory import (
    KITTI_LENGTHS_M,
    RelativePoseError,
    TrajectoryMetrics,
    align_se3,
    ate_per_axis_rmse,
    ate_rmse,
    ate_rotation_rmse_deg,
    kitti_relative_error,
    rpe,
    trajectory_length_m,
    trajectory_metrics,
    umeyama_alignment,
    unaligned_error,
)

__all__ = [
    "KITTI_LENGTHS_M",
    "MeshMetrics",
    "RelativePoseError",
    "TrajectoryMetrics",
    "align_se3",
    "ate_per_axis_rmse",
    "ate_rmse",
    "ate_rotation_rmse_deg",
    "kitti_relative_error",
    "mesh_metrics",
    "rpe",
    "surface_distances",
    "trajectory_length_m",
    "trajectory_metrics",
    "umeyama_alignment",
    "unaligned_error",
    "visible_face_mask",
]
