"""KISS-ICP's start: the first scans registered by point-to-plane ICP
(``KissIcpOdometry(start_scans=...)``, ``odometry.kiss_icp_start_scans``)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from frontends.odometry.kiss import KissIcpOdometry

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _angle_deg(T: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()))


def test_kiss_icp_start_scans_keep_the_first_metres_along_blank_walls(tmp_path: Path) -> None:
    """A sequence that starts at 8.6 m/s on a street of long blank walls (the generator's sparse
    street along KITTI 00): point-to-plane ICP measures each start step, and with the first
    scans registered that way the along-track distance after 30 scans stays within 1.5 m."""
    from frontends.sources import make_source

    poses, calib = DATA / "kitti" / "poses" / "00.txt", DATA / "kitti" / "sequences" / "00"
    if not (poses.is_file() and (calib / "calib.txt").is_file()):
        pytest.skip(f"KITTI 00 poses or calib not found under {DATA / 'kitti'}")
    source = make_source(
        "generated",
        kind="lidar",
        trajectory="kitti",
        kitti_poses=poses,
        kitti_calib=calib / "calib.txt",
        root=tmp_path,
        num_frames=30,
        street_style="sparse",
        azimuth_steps=1024,
        start=0,
    )
    frames = list(source)
    odometry = KissIcpOdometry(data={"max_range": 100.0, "min_range": 0.0}, start_scans=8)
    for previous, current in itertools.pairwise(frames[:4]):
        T_true = np.linalg.inv(previous.T_W_S_gt) @ current.T_W_S_gt
        T = odometry.start_motion(previous.points, current.points)
        assert T is not None
        np.testing.assert_allclose(T[:3, 3], T_true[:3, 3], atol=0.05)
        assert _angle_deg(np.linalg.inv(T_true) @ T) < 0.2
    poses_W = [odometry.register(frame).T_W_S for frame in frames]
    travelled = np.linalg.norm(poses_W[-1][:3, 3] - poses_W[0][:3, 3])
    truth = np.linalg.norm(frames[-1].T_W_S_gt[:3, 3] - frames[0].T_W_S_gt[:3, 3])
    assert abs(travelled - truth) < 1.5


def test_kiss_icp_start_motion_refuses_scans_that_do_not_overlap() -> None:
    rng = np.random.default_rng(3)
    odometry = KissIcpOdometry(start_scans=4)
    scan = rng.uniform(-20, 20, (5000, 3))
    assert odometry.start_motion(scan, scan + 500.0) is None
