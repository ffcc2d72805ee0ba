"""Why KISS-ICP loses the MulRan keyframes: its registration given a perfect prediction.

KISS-ICP predicts each scan's pose with a constant-velocity model (the last scan-to-scan motion
repeated) and registers the scan to its local map from there, with correspondences up to three
times an adaptive threshold. :func:`kiss_icp_with_reference_prediction` replays the same
registration (the run's ``odometry.kiss_icp`` settings, the project's wrapper) with the
prediction replaced by the reference's own motion: if the registration then tracks, what fails on
the keyframes is the prediction (metres off at 0.1-45 m spacing), not the registration.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


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
