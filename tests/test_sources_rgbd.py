"""RGB-D sources: TUM RGB-D, ICL-NUIM, Replica and 7-Scenes layouts, on written and real files."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from frontends.errors import DatasetError
from frontends.frame import Intrinsics
from frontends.sources import make_source
from frontends.sources._io import DepthOptions, associate
from frontends.sources.tum import FLIP_Y, icl_folder_candidates
from tests.dataset_files import (
    assert_one_line_error,
    make_tum,
    random_pose,
    real,
    tum_row,
    write_depth,
    write_rgb,
)


def test_associate_matches_tum_greedy_rule():
    rgb = np.array([0.0, 0.033, 0.066, 0.1, 0.5])
    depth = np.array([0.01, 0.03, 0.045, 0.09, 0.2])
    matches = associate(rgb, depth, 0.02)
    # 0.033<->0.03 (0.003) first, then 0.1<->0.09, then 0.0<->0.01; 0.066 has none left in range.
    assert matches == [(0, 0), (1, 1), (3, 3)]
    assert associate(rgb, np.array([5.0]), 0.02) == []


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
