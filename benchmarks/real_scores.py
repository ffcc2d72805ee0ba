"""Scores of ``benchmarks.bench_real``: trajectories against reference poses, the motion per scan
of a run without ground truth, a mesh against the scan points it was built from, and why KISS-ICP
loses the MulRan keyframes (:func:`kiss_icp_with_reference_prediction`: the same registration
predicted with the reference's motion instead of constant velocity; if it then tracks, what fails
is the prediction, not the registration)."""

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
        "lost_step_median_length_m": _median_or_zero(ref_length[step_error > LOST_STEP_M]),
        "kept_step_median_length_m": _median_or_zero(ref_length[step_error <= LOST_STEP_M]),
    }


def _median_or_zero(values: np.ndarray) -> float:
    return float(np.median(values)) if len(values) else 0.0


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
    out = {"vertices": len(mesh.vertices), "faces": len(mesh.faces), "points": len(points)}
    for side, near, d in (
        ("vertex_to_points", "vertices_near", vertex_distance),
        ("points_to_mesh", "points_near", point_distance),
    ):
        out.update(
            {
                f"{side}_median_m": float(np.median(d)),
                f"{side}_p90_m": float(np.percentile(d, 90)),
                near: float(np.mean(d <= NEAR_M)),
            }
        )
    return {**out, "vertex_distances_m": vertex_distance}


def _orthonormal(poses: np.ndarray) -> np.ndarray:
    """Reference poses stored with 6 digits: re-orthonormalise their rotations (Sophus checks)."""
    from scipy.spatial.transform import Rotation

    poses = np.array(poses, dtype=np.float64)
    poses[:, :3, :3] = Rotation.from_matrix(poses[:, :3, :3]).as_matrix()
    return poses


def constant_velocity_error(reference: np.ndarray) -> np.ndarray:
    """How far the constant-velocity prediction lands from each reference pose (metres)."""
    reference = _orthonormal(reference)
    errors = []
    for i in range(2, len(reference)):
        last_motion = np.linalg.inv(reference[i - 2]) @ reference[i - 1]
        predicted = reference[i - 1] @ last_motion
        errors.append(np.linalg.norm(predicted[:3, 3] - reference[i, :3, 3]))
    return np.asarray(errors)


def kiss_icp_with_reference_prediction(
    files: list[Path], reference: np.ndarray, config_yaml: Path
) -> np.ndarray:
    """KISS-ICP poses of ``files`` when every prediction is the reference motion (first pose at
    the identity, as in a run)."""
    import yaml

    from frontends.odometry.kiss import KissIcpConfig
    from frontends.sources.pcd_folder import read_pcd_points

    settings = yaml.safe_load(config_yaml.read_text())["odometry"]["kiss_icp"]
    settings["data"]["deskew"] = False  # the keyframes are de-skewed and carry no point times
    from kiss_icp.kiss_icp import KissICP

    kiss = KissICP(KissIcpConfig(**settings).to_kiss())
    reference = _orthonormal(reference)
    poses = []
    for i, path in enumerate(files):
        if i > 0:
            kiss.last_delta = np.linalg.inv(reference[i - 1]) @ reference[i]
        kiss.register_frame(read_pcd_points(path), np.array([]))
        poses.append(np.array(kiss.last_pose))
    return np.asarray(poses)
