"""Scores of ``benchmarks.bench_real``: trajectories against reference poses, the motion per scan
of a run without ground truth, and a mesh against the scan points it was built from."""

from __future__ import annotations

from pathlib import Path

import numpy as np

MAX_SURFACE_QUERIES = 50_000
"""Scan points whose distance to the mesh is computed (a seeded subset; every point is used for
the mesh-to-points direction, which is a KD-tree query)."""
NEAR_M = 0.5
"""A point or vertex this close to the other side counts as "near" (half the 1 m map voxel)."""
LOST_STEP_M = 1.0
"""A scan-to-scan motion more than this far from the reference's counts as a tracking failure."""


def _relative_steps(poses: np.ndarray) -> np.ndarray:
    return np.linalg.inv(poses[:-1]) @ poses[1:]


def tracking_scores(est: np.ndarray, reference: np.ndarray) -> dict[str, float | int]:
    """ATE (SE(3)-aligned: RMSE, per world axis, rotation) and how often a scan-to-scan motion
    is off: the error of each relative motion against the reference's."""
    from slam.evaluation.metrics.trajectory import trajectory_metrics

    metrics = trajectory_metrics(est, reference)
    est_steps, ref_steps = _relative_steps(est), _relative_steps(reference)
    step_error = np.linalg.norm(est_steps[:, :3, 3] - ref_steps[:, :3, 3], axis=1)
    ref_length = np.linalg.norm(ref_steps[:, :3, 3], axis=1)
    return {
        "ate_m": metrics.ate_rmse_m,
        "ate_xyz_m": [metrics.ate_x_rmse_m, metrics.ate_y_rmse_m, metrics.ate_z_rmse_m],
        "ate_rot_deg": metrics.ate_rot_rmse_deg,
        "length_m": float(ref_length.sum()),
        "est_length_m": float(np.linalg.norm(est_steps[:, :3, 3], axis=1).sum()),
        "step_error_median_m": float(np.median(step_error)),
        "steps": len(step_error),
        "steps_lost": int(np.count_nonzero(step_error > LOST_STEP_M)),
        "lost_step_median_length_m": float(np.median(ref_length[step_error > LOST_STEP_M]))
        if np.any(step_error > LOST_STEP_M)
        else 0.0,
        "kept_step_median_length_m": float(np.median(ref_length[step_error <= LOST_STEP_M]))
        if np.any(step_error <= LOST_STEP_M)
        else 0.0,
    }


def reference_floor(other: np.ndarray, reference: np.ndarray) -> dict[str, float | int]:
    """How far a second estimate of the same poses (FAST-LIO2's odometry before loop closure) is
    from the reference: the scale of what "agrees with the reference" can mean."""
    return tracking_scores(other, reference)


def step_statistics(poses: np.ndarray) -> dict[str, float]:
    """Motion per scan of a run without ground truth (metres and degrees per scan)."""
    steps = _relative_steps(poses)
    length = np.linalg.norm(steps[:, :3, 3], axis=1)
    yaw = np.degrees(np.arctan2(steps[:, 1, 0], steps[:, 0, 0]))
    return {
        "scans": len(poses),
        "step_median_m": float(np.median(length)),
        "step_min_m": float(length.min()),
        "step_max_m": float(length.max()),
        "step_change_max_m": float(np.abs(np.diff(length)).max()) if len(length) > 1 else 0.0,
        "yaw_abs_max_deg": float(np.abs(yaw).max()),
        "lateral_vertical_max_m": float(np.abs(steps[:, 1:3, 3]).max()),
        "path_m": float(length.sum()),
    }


def map_points(files: list[Path], poses: np.ndarray, config_yaml: Path) -> np.ndarray:
    """Every scan point the run's submaps keep (``submaps.min_range_m`` to ``max_range_m`` from
    the sensor, as resolved in the run's config.yaml), placed in the world by ``poses``."""
    import yaml

    from frontends.sources.pcd_folder import read_pcd_points

    submaps = yaml.safe_load(config_yaml.read_text())["submaps"]
    low, high = float(submaps["min_range_m"]), float(submaps["max_range_m"])
    placed = []
    for path, pose in zip(files, poses, strict=True):
        points = read_pcd_points(path)
        r = np.linalg.norm(points, axis=1)
        points = points[(r >= low) & (r <= high)]
        placed.append(points @ pose[:3, :3].T + pose[:3, 3])
    return np.concatenate(placed)


def mesh_point_distances(mesh_path: Path, points: np.ndarray) -> dict[str, float | int]:
    """Both directions between a mesh and the scan points: mesh vertex -> nearest point (is
    what the mesh shows really there?) and point -> mesh surface (is what was scanned in the
    mesh? the neural map leaves out sparsely seen voxels, so this side has a long tail)."""
    import trimesh
    from scipy.spatial import cKDTree

    from slam.evaluation.metrics.mesh import surface_distances

    mesh = trimesh.load(mesh_path, process=False)
    vertex_distance, _ = cKDTree(points).query(np.asarray(mesh.vertices), workers=-1)
    rng = np.random.default_rng(0)
    subset = points[rng.choice(len(points), min(len(points), MAX_SURFACE_QUERIES), replace=False)]
    point_distance = surface_distances(subset, mesh)
    return {
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
        "points": len(points),
        "vertex_to_points_median_m": float(np.median(vertex_distance)),
        "vertex_to_points_p90_m": float(np.percentile(vertex_distance, 90)),
        "vertices_near": float(np.mean(vertex_distance <= NEAR_M)),
        "points_to_mesh_median_m": float(np.median(point_distance)),
        "points_to_mesh_p90_m": float(np.percentile(point_distance, 90)),
        "points_near": float(np.mean(point_distance <= NEAR_M)),
        "vertex_distances_m": vertex_distance,
    }
