"""LiDAR sources (KITTI layout, real KITTI scans), read-ahead and the source registry."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from frontends.depth import depth_to_points
from frontends.errors import DatasetError
from frontends.frame import Intrinsics
from frontends.sources import make_source
from frontends.sources.kitti import (
    camera_to_lidar_poses,
    read_kitti_bin,
    read_kitti_calib_tr,
    read_kitti_poses,
)
from tests.dataset_files import (
    DATA,
    assert_one_line_error,
    random_pose,
    real,
)

TR = np.array(
    [
        [0.0, -1.0, 0.0, -0.01],
        [0.0, 0.0, -1.0, -0.07],
        [1.0, 0.0, 0.0, -0.27],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def make_kitti(root: Path, seq: str = "03", n: int = 3, with_poses: bool = True) -> list:
    rng = np.random.default_rng(0)
    seq_dir = root / "sequences" / seq
    (seq_dir / "velodyne").mkdir(parents=True)
    scans = []
    for i in range(n):
        scan = rng.normal(0, 10, (100 + i, 4)).astype(np.float32)
        scan.tofile(seq_dir / "velodyne" / f"{i:06d}.bin")
        scans.append(scan)
    p = " ".join(["1"] + ["0"] * 11)
    tr = " ".join(f"{v:.12e}" for v in TR[:3].ravel())
    (seq_dir / "calib.txt").write_text(f"P0: {p}\nP1: {p}\nP2: {p}\nP3: {p}\nTr: {tr}\n")
    (seq_dir / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n)))
    poses = [random_pose(rng) for _ in range(n)]
    if with_poses:
        (root / "poses").mkdir()
        rows = [" ".join(f"{v:.12e}" for v in pose[:3].ravel()) for pose in poses]
        (root / "poses" / f"{seq}.txt").write_text("\n".join(rows) + "\n")
    return [scans, np.stack(poses)]


def test_kitti_layout(tmp_path):
    scans, poses_cam = make_kitti(tmp_path)
    source = make_source("kitti", root=tmp_path, sequence="3", correct_vertical_angle=False)
    assert source.sensor == "lidar" and len(source) == 3
    frame = source[1]
    assert frame.points.dtype == np.float64 and frame.points.shape == (101, 3)
    np.testing.assert_array_equal(frame.points, scans[1][:, :3].astype(np.float64))
    np.testing.assert_array_equal(source.reflectance(1), scans[1][:, 3])
    assert frame.colors is None and frame.timestamp == pytest.approx(0.1)
    expected = np.linalg.inv(TR) @ poses_cam @ TR
    np.testing.assert_allclose(source.gt_poses, expected, atol=1e-9)
    np.testing.assert_allclose(frame.T_W_S_gt, expected[1], atol=1e-9)

    sliced = make_source("kitti", root=tmp_path, sequence="03", frames=slice(1, None))
    assert len(sliced) == 2 and sliced[0].index == 0
    np.testing.assert_allclose(sliced.gt_poses, expected[1:], atol=1e-9)
    # KISS-ICP's vertical-angle correction moves points slightly, never far.
    shift = np.linalg.norm(sliced[0].points - scans[1][:, :3], axis=1)
    assert 0 < shift.max() < 0.01 * np.linalg.norm(scans[1][:, :3], axis=1).max()


@pytest.mark.parametrize("depth", [1, 2, 5])
def test_read_ahead_yields_the_frames_in_order_and_raises_at_a_bad_one(tmp_path, depth):
    """Frames loaded ahead on a background thread are the frames, in order; a truncated scan
    raises its one-line error when its turn comes, after the frames before it."""
    make_kitti(tmp_path, n=4)
    source = make_source("kitti", root=tmp_path, sequence="3")
    for ahead, frame in zip(source.read_ahead(depth), source, strict=True):
        assert ahead.index == frame.index
        np.testing.assert_array_equal(ahead.points, frame.points)
    velodyne = tmp_path / "sequences" / "03" / "velodyne"
    (velodyne / "000002.bin").write_bytes((velodyne / "000002.bin").read_bytes()[:-5])
    seen = []
    with pytest.raises(DatasetError) as exc:
        for frame in source.read_ahead(depth):
            seen.append(frame.index)
    assert seen == [0, 1]
    assert_one_line_error(exc, "000002.bin", "truncated")


def test_kitti_without_poses_has_no_ground_truth(tmp_path):
    make_kitti(tmp_path, with_poses=False)
    source = make_source("kitti", root=tmp_path, sequence="03")
    assert source.gt_poses is None and source[0].T_W_S_gt is None


def test_kitti_bad_inputs(tmp_path):
    with pytest.raises(DatasetError) as exc:
        make_source("kitti", root=tmp_path, sequence="00")
    assert_one_line_error(exc, "sequences/00")

    make_kitti(tmp_path)
    velodyne = tmp_path / "sequences" / "03" / "velodyne"
    (velodyne / "000001.bin").write_bytes((velodyne / "000001.bin").read_bytes()[:-5])
    source = make_source("kitti", root=tmp_path, sequence="03")
    with pytest.raises(DatasetError) as exc:
        source[1]
    assert_one_line_error(exc, "000001.bin", "truncated")

    (velodyne / "000002.bin").write_bytes(b"")
    with pytest.raises(DatasetError) as exc:
        source[2]
    assert_one_line_error(exc, "000002.bin", "empty")

    # a non-finite reflectance is no coordinate: the scan is read; a NaN coordinate is refused
    scan = np.ones((10, 4), np.float32)
    scan[3, 3] = np.nan
    scan.tofile(velodyne / "000000.bin")
    assert np.isnan(read_kitti_bin(velodyne / "000000.bin")[3, 3])
    scan[7, 2] = -np.inf
    scan.tofile(velodyne / "000000.bin")
    with pytest.raises(DatasetError) as exc:
        source[0]
    assert_one_line_error(exc, "000000.bin", "NaN/inf coordinates")

    (tmp_path / "sequences" / "03" / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(DatasetError) as exc:
        make_source("kitti", root=tmp_path, sequence="03")
    assert_one_line_error(exc, "times.txt", "2 timestamps for 3 scans")


def test_kitti_real_calibration_and_ground_truth():
    tr = read_kitti_calib_tr(real("kitti/sequences/00/calib.txt"))
    np.testing.assert_allclose(tr[:3, :3] @ tr[:3, :3].T, np.eye(3), atol=1e-5)
    poses = camera_to_lidar_poses(read_kitti_poses(real("kitti/poses/00.txt")), tr)
    assert poses.shape == (4541, 4, 4)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-6)
    # In the LiDAR frame (x forward, z up) the car drives forward and stays level at the start.
    start = poses[50, :3, 3]
    assert start[0] > 20 and abs(start[2]) < 0.05 * start[0]
    # Sequence 00 comes back to within ~1.2 m of its start near frame 4447.
    assert np.linalg.norm(poses[4447, :3, 3] - poses[0, :3, 3]) < 2.0


def test_kitti_real_scans(tmp_path):
    folder = real("kitti/real_scans")
    scan = read_kitti_bin(folder / "000010.bin")
    assert scan.dtype == np.float32 and scan.shape[1] == 4 and 100_000 < len(scan) < 140_000
    assert 0.0 <= scan[:, 3].min() and scan[:, 3].max() <= 1.0
    # The real scans as a sequence (links, not copies) with the real calibration.
    velodyne = tmp_path / "sequences" / "00" / "velodyne"
    velodyne.mkdir(parents=True)
    for i, name in enumerate(["000010", "000011", "000012"]):
        os.symlink(folder / f"{name}.bin", velodyne / f"{i:06d}.bin")
    os.symlink(real("kitti/sequences/00/calib.txt"), tmp_path / "sequences" / "00" / "calib.txt")
    (tmp_path / "sequences" / "00" / "times.txt").write_text("0.0\n0.1\n0.2\n")
    source = make_source("kitti", root=tmp_path, sequence="00")
    assert len(source) == 3 and source.gt_poses is None
    assert len(source[2].points) == len(read_kitti_bin(folder / "000012.bin"))


# ------------------------------------------------------------------------------ TUM and ICL


def test_unknown_source_name():
    with pytest.raises(DatasetError) as exc:
        make_source("kitty", root=".", sequence="00")
    assert_one_line_error(exc, "kitty", "kitti")


def test_depth_to_points_on_real_depth_has_unit_normals_facing_the_sensor():
    root = real("7scenes_redkitchen")
    raw = cv2.imread(str(root / "seq-01" / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED)
    depth = np.where(raw == 65535, 0, raw).astype(np.float32) / 1000
    cloud = depth_to_points(depth, Intrinsics(585, 585, 320, 240, 640, 480))
    np.testing.assert_allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-9)
    assert np.all(np.einsum("ij,ij->i", cloud.normals, cloud.points) <= 0)


def test_seven_scenes_poses_are_proper_rotations():
    if not (DATA / "7scenes_redkitchen").is_dir():
        pytest.skip(f"real 7-Scenes frames not found under {DATA}")
    source = make_source("7scenes", root=DATA / "7scenes_redkitchen", sequence="seq-01")
    R = source.gt_poses[:, :3, :3]
    assert np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() < 1e-9
    assert np.allclose(np.linalg.det(R), 1.0)
