"""Dataset sources on files written in their exact layouts, and on the small real data."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from frontends.depth import depth_to_points
from frontends.errors import DatasetError
from frontends.frame import Intrinsics
from frontends.sources._io import DepthOptions, associate
from frontends.sources.base import make_source
from frontends.sources.kitti import (
    camera_to_lidar_poses,
    read_kitti_bin,
    read_kitti_calib_tr,
    read_kitti_poses,
)
from frontends.sources.tum import FLIP_Y, icl_folder_candidates

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def real(path: str) -> Path:
    full = DATA / path
    if not full.exists():
        pytest.skip(f"real data {full} is absent")
    return full


def assert_one_line_error(exc: pytest.ExceptionInfo, *needles: str) -> None:
    message = str(exc.value)
    assert "\n" not in message
    for needle in needles:
        assert needle in message, f"{needle!r} not in {message!r}"


def random_pose(rng: np.random.Generator, step: float = 0.1) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.2, 3)).as_matrix()
    pose[:3, 3] = rng.normal(0, step, 3)
    return pose


def write_depth(path: Path, depth_m: np.ndarray, scale: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.round(depth_m * scale).astype(np.uint16))


def write_rgb(path: Path, shape=(480, 640), value: int = 128) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    image = np.full((*shape, 3), value, np.uint8)
    image[..., 0] = 10  # blue channel in OpenCV order
    assert cv2.imwrite(str(path), image)


def tum_row(stamp: float, pose: np.ndarray) -> str:
    q = Rotation.from_matrix(pose[:3, :3]).as_quat()
    return f"{stamp:.6f} " + " ".join(f"{v:.9f}" for v in (*pose[:3, 3], *q))


# --------------------------------------------------------------------------------------- KITTI

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


def test_associate_matches_tum_greedy_rule():
    rgb = np.array([0.0, 0.033, 0.066, 0.1, 0.5])
    depth = np.array([0.01, 0.03, 0.045, 0.09, 0.2])
    matches = associate(rgb, depth, 0.02)
    # 0.033<->0.03 (0.003) first, then 0.1<->0.09, then 0.0<->0.01; 0.066 has none left in range.
    assert matches == [(0, 0), (1, 1), (3, 3)]
    assert associate(rgb, np.array([5.0]), 0.02) == []


def make_tum(folder: Path, n: int = 4) -> np.ndarray:
    rng = np.random.default_rng(2)
    rgb_lines, depth_lines, gt_lines = ["# rgb"], ["# depth"], ["# gt"]
    for i in range(n):
        t = 100.0 + i / 30
        write_rgb(folder / "rgb" / f"{t:.6f}.png")
        write_depth(folder / "depth" / f"{t + 0.004:.6f}.png", np.full((480, 640), 1.0 + i), 5000)
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
    # Extra depth image far in time: no colour partner.
    write_depth(folder / "depth" / "200.000000.png", np.full((480, 640), 1.0), 5000)
    depth_lines.append("200.000000 depth/200.000000.png")
    poses = []
    for k in range(3 * n + 3):
        pose = random_pose(rng)
        poses.append(pose)
        gt_lines.append(tum_row(99.99 + k / 100, pose))
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (folder / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return np.stack(poses)


def test_tum_layout(tmp_path):
    gt = make_tum(tmp_path / "rgbd_dataset_freiburg1_xyz")
    source = make_source("tum", root=tmp_path, sequence="freiburg1_xyz")
    assert source.sensor == "rgbd" and len(source) == 4
    frame = source[2]
    assert frame.depth.dtype == np.float32 and frame.depth.shape == (480, 640)
    np.testing.assert_allclose(frame.depth, 3.0)
    np.testing.assert_allclose(frame.points[:, 2], 3.0, atol=1e-6)
    assert frame.rgb.dtype == np.uint8 and tuple(frame.rgb[0, 0]) == (128, 128, 10)
    assert frame.colors.shape == frame.points.shape and frame.normals.shape == frame.points.shape
    assert frame.timestamp == pytest.approx(100.0 + 2 / 30)
    assert frame.intrinsics.fy > 0
    # Frame at t = 100 + i/30 pairs with the ground-truth row nearest in time (rows every 10 ms).
    expected_rows = [round((100.0 + i / 30 - 99.99) * 100) for i in range(4)]
    np.testing.assert_allclose(source.gt_poses, gt[expected_rows], atol=1e-6)


def test_tum_intrinsics_follow_the_camera_and_can_be_overridden(tmp_path):
    from frontends.sources.tum import tum_intrinsics_for

    # The published colour calibrations of the three TUM cameras, picked by the sequence name.
    assert tum_intrinsics_for("rgbd_dataset_freiburg1_desk").fx == 517.3
    assert tum_intrinsics_for("freiburg2_xyz").cy == 249.7
    assert tum_intrinsics_for("fr3_office").fy == 539.2
    assert tum_intrinsics_for("my_recording").fx == 525.0
    make_tum(tmp_path / "rgbd_dataset_freiburg3_long_office_household")
    source = make_source("tum", root=tmp_path, sequence="freiburg3_long_office_household")
    assert (source.intrinsics.fx, source.intrinsics.cx) == (535.4, 320.1)
    own = {"fx": 600.0, "fy": 601.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}
    source = make_source(
        "tum", root=tmp_path, sequence="freiburg3_long_office_household", intrinsics=own
    )
    assert source.intrinsics.fy == 601.0


def test_tum_frames_without_ground_truth_are_fed_not_scored(tmp_path):
    folder = tmp_path / "rgbd_dataset_freiburg2_xyz"
    make_tum(folder)
    rows = (folder / "groundtruth.txt").read_text().splitlines()
    # Drop the ground truth within 20 ms of the third frame (t = 100.0667): rows k = 6..9 at
    # t = 99.99 + k / 100 (line k + 1, after the comment line).
    (folder / "groundtruth.txt").write_text("\n".join(rows[:7] + rows[11:]) + "\n")
    source = make_source("tum", root=tmp_path, sequence="freiburg2_xyz")
    assert len(source) == 4
    assert source[2].T_W_S_gt is None and np.isnan(source.gt_poses[2]).all()
    assert np.isfinite(source.gt_poses[[0, 1, 3]]).all()


def test_rgbd_image_folder_with_intrinsics_file(tmp_path):
    """The documented image-folder layout: rgb/<t>.png, depth/<t>.png, intrinsics.txt."""
    folder = tmp_path / "my_rgbd"
    for i in range(3):
        write_rgb(folder / "rgb" / f"{i / 10:.1f}.png", shape=(240, 320))
        write_depth(folder / "depth" / f"{i / 10:.1f}.png", np.full((240, 320), 1.5), 1000)
    (folder / "intrinsics.txt").write_text(
        "# fx fy cx cy width height depth_scale\n300 300 160 120 320 240 1000\n"
    )
    source = make_source("tum", root=tmp_path, sequence="my_rgbd")
    assert len(source) == 3 and source.gt_poses is None
    assert source.intrinsics.fx == 300.0 and source.depth_scale == 1000.0
    np.testing.assert_allclose(source[1].depth, 1.5)
    assert source[2].timestamp == pytest.approx(0.2)


def test_tum_associations_file_and_missing_image(tmp_path):
    folder = tmp_path / "seq"
    make_tum(folder)
    (folder / "associations.txt").write_text(
        "100.000000 rgb/100.000000.png 100.004000 depth/100.004000.png\n"
        "100.033333 rgb/100.033333.png 100.037333 depth/100.037333.png\n"
    )
    source = make_source("tum", root=tmp_path, sequence="seq")
    assert len(source) == 2
    np.testing.assert_allclose(source[1].depth, 2.0)
    (folder / "depth" / "100.037333.png").unlink()
    with pytest.raises(DatasetError) as exc:
        make_source("tum", root=tmp_path, sequence="seq")
    assert_one_line_error(exc, "100.037333.png")


def test_tum_all_zero_depth_frame_is_an_error(tmp_path):
    folder = tmp_path / "seq"
    make_tum(folder)
    write_depth(folder / "depth" / "100.070667.png", np.zeros((480, 640)), 5000)
    source = make_source("tum", root=tmp_path, sequence="seq")
    source[0]
    with pytest.raises(DatasetError) as exc:
        source[2]
    assert_one_line_error(exc, "100.070667.png", "no valid")


def test_depth_options_from_dict_and_unknown_key(tmp_path):
    make_tum(tmp_path / "seq")
    source = make_source("tum", root=tmp_path, sequence="seq", depth_options={"stride": 8})
    assert source.depth_options == DepthOptions(stride=8)
    assert len(source[0].points) < 640 * 480 / 50
    with pytest.raises(DatasetError) as exc:
        make_source("tum", root=tmp_path, sequence="seq", depth_options={"strid": 8})
    assert_one_line_error(exc, "depth_options", "strid")


def test_tum_missing_folder(tmp_path):
    with pytest.raises(DatasetError) as exc:
        make_source("tum", root=tmp_path, sequence="fr1_desk")
    assert_one_line_error(exc, str(tmp_path), "fr1_desk")


def test_icl_names():
    assert "living_room_traj3n_frei_png" in icl_folder_candidates("lr-kt3n")
    assert "traj0_frei_png" in icl_folder_candidates("of-kt0")
    assert "lr_kt2" in icl_folder_candidates("lr-kt2")
    assert icl_folder_candidates("my_folder") == ["my_folder"]


def test_icl_tum_release_layout(tmp_path):
    folder = tmp_path / "living_room_traj1n_frei_png"
    rng = np.random.default_rng(5)
    lines, gt_lines, poses = [], [], []
    for i in range(4):
        write_rgb(folder / "rgb" / f"{i}.png")
        write_depth(folder / "depth" / f"{i}.png", np.full((480, 640), 2.0), 5000)
        lines.append(f"{i} depth/{i}.png {i} rgb/{i}.png")
        if i > 0:  # as in the release, frame 0 has no ground truth
            poses.append(random_pose(rng))
            gt_lines.append(tum_row(i, poses[-1]).replace(f"{i:.6f}", str(i), 1))
    (folder / "associations.txt").write_text("\n".join(lines) + "\n")
    (tmp_path / "livingRoom1.gt.freiburg").write_text("\n".join(gt_lines) + "\n")
    source = make_source("icl", root=tmp_path, sequence="lr-kt1n")
    assert len(source) == 4  # frame 0 has no ground truth: it is still fed, just not scored
    assert source[0].T_W_S_gt is None and np.isnan(source.gt_poses[0]).all()
    assert source.intrinsics.fy == 480.0 and source.intrinsics.fx == 481.2
    np.testing.assert_allclose(source.gt_poses[1:], FLIP_Y @ np.stack(poses) @ FLIP_Y, atol=1e-6)
    np.testing.assert_allclose(source[1].T_W_S_gt, source.gt_poses[1])
    assert source[1].timestamp == 1.0
    np.testing.assert_allclose(np.linalg.det(source.gt_poses[1:, :3, :3]), 1.0, atol=1e-6)


def test_icl_small_layout_count_mismatch(tmp_path):
    folder = tmp_path / "icl"
    for i in (1, 2, 3):
        write_rgb(folder / "color" / f"{i}.png")
        write_depth(folder / "depth" / f"{i}.png", np.full((480, 640), 2.0), 5000)
    (folder / "pose.txt").write_text("0 0 0 0 0 0 1\n0 0 1 0 0 0 1\n")
    with pytest.raises(DatasetError) as exc:
        make_source("icl", root=tmp_path, sequence="icl")
    assert_one_line_error(exc, "pose.txt", "2 poses for 3 depth images")


def world_points(frame, pose: np.ndarray) -> np.ndarray:
    return frame.points @ pose[:3, :3].T + pose[:3, 3]


def test_icl_real_frames_overlap_under_ground_truth():
    root = real("icl_nuim_livingroom_5")
    source = make_source(
        "icl", root=root.parent, sequence=root.name, depth_options=DepthOptions(stride=4)
    )
    assert len(source) == 5 and source.intrinsics.fy > 0
    first, last = source[0], source[4]
    a = world_points(first, first.T_W_S_gt)
    b = world_points(last, last.T_W_S_gt)
    distance, _ = cKDTree(a).query(b)
    assert np.median(distance) < 0.02
    # The opposite sign choice (fy > 0 with the poses as published) does not line up.
    raw = np.loadtxt(root / "pose.txt")
    published = [np.eye(4), np.eye(4)]
    for pose, row in zip(published, raw[[0, 4]], strict=True):
        pose[:3, :3] = Rotation.from_quat(row[3:]).as_matrix()
        pose[:3, 3] = row[:3]
    distance, _ = cKDTree(world_points(first, published[0])).query(world_points(last, published[1]))
    assert np.median(distance) > 0.04


# ------------------------------------------------------------------------------ Replica


def make_replica(root: Path, numbers=(0, 1, 2), traj_rows: int = 5) -> np.ndarray:
    rng = np.random.default_rng(7)
    results = root / "room0" / "results"
    for n in numbers:
        write_rgb(results / f"frame{n:06d}.jpg", shape=(68, 120))
        write_depth(results / f"depth{n:06d}.png", np.full((68, 120), 1.5 + n), 6553.5)
    poses = np.stack([random_pose(rng) for _ in range(traj_rows)])
    np.savetxt(root / "room0" / "traj.txt", poses.reshape(-1, 16))
    camera = {"w": 120, "h": 68, "fx": 60.0, "fy": 60.0, "cx": 59.5, "cy": 33.5, "scale": 6553.5}
    (root / "cam_params.json").write_text(json.dumps({"camera": camera}))
    return poses


def test_replica_layout(tmp_path):
    poses = make_replica(tmp_path, numbers=(0, 2, 3))
    source = make_source("replica", root=tmp_path, sequence="room0")
    assert len(source) == 3 and source.gt_mesh_path is None
    assert source.intrinsics == Intrinsics(60.0, 60.0, 59.5, 33.5, 120, 68)
    np.testing.assert_allclose(source.gt_poses, poses[[0, 2, 3]], atol=1e-12)
    frame = source[1]
    np.testing.assert_allclose(frame.points[:, 2], 3.5, atol=1e-4)
    assert frame.timestamp == 2.0
    (tmp_path / "room0_mesh.ply").write_text("ply\n")
    assert source.gt_mesh_path == tmp_path / "room0_mesh.ply"


def test_replica_bad_inputs(tmp_path):
    make_replica(tmp_path, numbers=(0, 1, 6), traj_rows=5)
    with pytest.raises(DatasetError) as exc:
        make_source("replica", root=tmp_path, sequence="room0")
    assert_one_line_error(exc, "traj.txt", "5 poses")
    (tmp_path / "room0" / "results" / "depth000006.png").unlink()
    with pytest.raises(DatasetError) as exc:
        make_source("replica", root=tmp_path, sequence="room0")
    assert_one_line_error(exc, "results", "unpaired frame numbers [6]")
    with pytest.raises(DatasetError) as exc:
        make_source("replica", root=tmp_path, sequence="office9")
    assert_one_line_error(exc, "office9")


def test_replica_real_frames_lie_on_the_mesh():
    import trimesh

    root = real("replica")
    source = make_source(
        "replica", root=root, sequence="office0", depth_options=DepthOptions(max_points=3000)
    )
    assert len(source) == 4
    assert source.intrinsics == Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)
    assert source.gt_mesh_path == root / "office0_mesh.ply"
    mesh = trimesh.load(source.gt_mesh_path, process=False)
    surface, _ = trimesh.sample.sample_surface(mesh, 300_000, seed=0)
    tree = cKDTree(surface)
    for frame in (source[0], source[3]):
        assert frame.depth.shape == (680, 1200) and frame.rgb.shape == (680, 1200, 3)
        distance, _ = tree.query(world_points(frame, frame.T_W_S_gt))
        assert np.median(distance) < 0.02


# ------------------------------------------------------------------------------ 7-Scenes


def test_sevenscenes_layout_and_bad_inputs(tmp_path):
    rng = np.random.default_rng(9)
    seq = tmp_path / "seq-02"
    poses = []
    for i in range(3):
        depth = np.full((480, 640), 1.2)
        raw = np.round(depth * 1000).astype(np.uint16)
        raw[:10] = 65535
        raw[10:20] = 0
        seq.mkdir(exist_ok=True)
        cv2.imwrite(str(seq / f"frame-{i:06d}.depth.png"), raw)
        write_rgb(seq / f"frame-{i:06d}.color.png")
        poses.append(random_pose(rng))
        np.savetxt(seq / f"frame-{i:06d}.pose.txt", poses[-1])
    source = make_source("7scenes", root=tmp_path, sequence="2")
    assert len(source) == 3 and source.intrinsics.fx == 585.0
    frame = source[1]
    assert np.all(frame.depth[:20] == 0) and np.allclose(frame.depth[20:], 1.2)
    assert frame.points[:, 1].min() > (20 - 240) * 1.2 / 585 - 1e-9
    np.testing.assert_allclose(source.gt_poses, np.stack(poses), atol=1e-12)

    (seq / "frame-000002.pose.txt").unlink()
    with pytest.raises(DatasetError) as exc:
        make_source("7scenes", root=tmp_path, sequence="seq-02")
    assert_one_line_error(exc, "seq-02", "2 pose files for 3 depth images")

    cv2.imwrite(str(seq / "frame-000000.depth.png"), np.zeros((480, 640), np.uint16))
    np.savetxt(seq / "frame-000002.pose.txt", poses[2])
    with pytest.raises(DatasetError) as exc:
        make_source("7scenes", root=tmp_path, sequence="seq-02")[0]
    assert_one_line_error(exc, "frame-000000.depth.png")


def test_sevenscenes_real_sequence():
    root = real("7scenes_redkitchen")
    source = make_source("7scenes", root=root, sequence="seq-01")
    assert len(source) == 400
    poses = source.gt_poses
    rotations = poses[:, :3, :3]
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-2)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 0.1 and steps.sum() > 0.5  # a hand-held camera at 30 Hz, moving
    first = source[0]
    assert first.depth.dtype == np.float32 and 0 < first.depth.max() < 10
    assert len(first.points) > 100_000
    # Frames 0 and 10 agree in the world frame under the ground-truth poses.
    sparse = make_source("7scenes", root=root, sequence="1", depth_options=DepthOptions(stride=4))
    a, b = sparse[0], sparse[10]
    distance, _ = cKDTree(world_points(a, a.T_W_S_gt)).query(world_points(b, b.T_W_S_gt))
    assert np.median(distance) < 0.02


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
