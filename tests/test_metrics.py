"""Trajectory and mesh metrics against answers known in closed form, and trajectory file I/O."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from frontends.errors import DatasetError
from slam.evaluation.metrics import (
    align_se3,
    ate_per_axis_rmse,
    ate_rmse,
    ate_rotation_rmse_deg,
    kitti_relative_error,
    mesh_metrics,
    rpe,
    surface_distances,
    trajectory_metrics,
    unaligned_error,
    visible_face_mask,
)
from slam.evaluation.metrics.trajectory import CAMERA_UP
from slam.run_folder.trajectory_io import read_kitti, read_tum, write_kitti, write_tum


def _se3(rotvec=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _random_trajectory(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = [np.eye(4)]
    for _ in range(n - 1):
        step = _se3(
            rng.normal(scale=0.05, size=3), rng.normal(scale=0.5, size=3) + np.array([1, 0, 0])
        )
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def _straight_line(n: int, step_m: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n) * step_m
    return poses


def _compose_steps(step: np.ndarray, n: int) -> np.ndarray:
    poses = [np.eye(4)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ step)
    return np.stack(poses)


# --- ATE / alignment ------------------------------------------------------------------------


def test_ate_is_zero_for_a_rigidly_moved_copy() -> None:
    gt = _random_trajectory(50)
    offset = _se3((0.3, -0.2, 1.0), (5.0, -3.0, 2.0))
    est = offset @ gt
    assert ate_rmse(est, gt) < 1e-9
    assert ate_rmse(est, gt, align=False) > 1.0
    np.testing.assert_allclose(align_se3(est, gt), np.linalg.inv(offset), atol=1e-9)


def test_ate_is_zero_for_a_pure_translation_offset() -> None:
    gt = _random_trajectory(30, seed=1)
    est = gt.copy()
    est[:, :3, 3] += [1.0, 2.0, -0.5]
    assert ate_rmse(est, gt) < 1e-9
    assert ate_rmse(est, gt, align=False) == pytest.approx(math.sqrt(1 + 4 + 0.25))


def test_ate_of_alternating_error_equals_its_amplitude() -> None:
    # Positions on a circle, estimate displaced +-d along z alternately: no rigid motion helps.
    n, d = 200, 0.1
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 0, 3], gt[:, 1, 3] = 10 * np.cos(angles), 10 * np.sin(angles)
    est = gt.copy()
    est[:, 2, 3] += d * (-1.0) ** np.arange(n)
    assert ate_rmse(est, gt) == pytest.approx(d, rel=1e-6)
    # The whole error is vertical: per axis it shows up in z only.
    np.testing.assert_allclose(ate_per_axis_rmse(est, gt), [0.0, 0.0, d], atol=1e-6)


def test_per_axis_ate_splits_the_ate() -> None:
    gt = _random_trajectory(60, seed=3)
    est = gt.copy()
    rng = np.random.default_rng(4)
    est[:, :3, 3] += rng.normal(size=(60, 3)) * [0.05, 0.1, 0.4]
    per_axis = ate_per_axis_rmse(est, gt)
    # ate_rmse is KISS-ICP's float32; the per-axis split is ours in float64
    assert np.sum(per_axis**2) == pytest.approx(ate_rmse(est, gt) ** 2, rel=1e-6)
    assert per_axis[2] > per_axis[1] > per_axis[0]
    metrics = trajectory_metrics(est, gt)
    assert metrics.ate_z_rmse_m == pytest.approx(per_axis[2])


def test_ate_matches_kiss_icp() -> None:
    kiss_metrics = pytest.importorskip("kiss_icp.metrics")
    gt = _random_trajectory(80, seed=2)
    est = _random_trajectory(80, seed=3)
    kiss_rot, kiss_trans = kiss_metrics.absolute_trajectory_error(list(gt), list(est))
    assert ate_rmse(est, gt) == pytest.approx(kiss_trans, rel=1e-6)
    assert ate_rotation_rmse_deg(est, gt) == pytest.approx(np.degrees(kiss_rot), rel=1e-6)
    # our alignment (which KISS-ICP does not return) gives the same ATE
    aligned = align_se3(est, gt) @ est
    own = np.sqrt(np.mean(np.sum((aligned[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=1)))
    assert own == pytest.approx(kiss_trans, rel=1e-6)
    assert ate_rmse(est, gt, align=False) > 2 * kiss_trans


def test_ate_of_a_standing_trajectory() -> None:
    gt = np.tile(np.eye(4), (3, 1, 1))
    est = gt.copy()
    est[:, :3, 3] = [1.0, 2.0, 3.0]
    assert ate_rmse(est, gt) < 1e-9
    np.testing.assert_allclose(align_se3(est, gt)[:3, 3], [-1.0, -2.0, -3.0], atol=1e-12)


def test_mismatched_lengths_are_rejected() -> None:
    with pytest.raises(ValueError, match="equal length"):
        ate_rmse(_straight_line(5, 1.0), _straight_line(6, 1.0))


# --- RPE ------------------------------------------------------------------------------------


def test_rpe_of_a_constant_step_error() -> None:
    n = 40
    gt = _compose_steps(_se3(t=(1.0, 0, 0)), n)
    est = _compose_steps(_se3((0, 0, np.radians(0.5)), (1.02, 0, 0)), n)
    result = rpe(est, gt, 1)
    assert result.num_pairs == n - 1
    assert result.trans_rmse_m == pytest.approx(0.02, rel=1e-6)
    assert result.rot_rmse_deg == pytest.approx(0.5, rel=1e-6)
    assert math.isnan(rpe(est[:1], gt[:1]).trans_rmse_m)


# --- KITTI relative error -------------------------------------------------------------------


def _segment_counts(lengths: np.ndarray, n: int, step: float) -> np.ndarray:
    """Segments per length on a uniform n-frame path: a segment starts every 10th frame and
    needs a frame beyond ``start + length``, i.e. ``start + length + step <= (n - 1) step``."""
    starts = np.arange(0, n, 10) * step
    return np.array([np.sum(starts + length + step <= (n - 1) * step) for length in lengths])


def test_kitti_error_of_a_constant_scale_drift() -> None:
    # 0.5 m steps: a 100 m segment ends at the first frame beyond 100 m, i.e. spans 100.5 m.
    step = 0.5
    gt = _straight_line(2000, step)
    est = _straight_line(2000, step * 1.01)
    t_err, r_err = kitti_relative_error(est, gt)
    lengths = np.arange(100, 900, 100)
    counts = _segment_counts(lengths, 2000, step)
    expected = np.average(1.0 * (lengths + step) / lengths, weights=counts)  # percent
    assert t_err == pytest.approx(expected, rel=1e-9)
    assert r_err == pytest.approx(0.0, abs=1e-9)


def test_kitti_error_of_a_constant_yaw_drift() -> None:
    step, omega = 0.5, np.radians(0.01)
    n = 2000
    gt = _compose_steps(_se3(t=(step, 0, 0)), n)
    est = _compose_steps(_se3((0, 0, omega), (step, 0, 0)), n)
    _, r_err = kitti_relative_error(est, gt)
    lengths = np.arange(100, 900, 100)
    frames = lengths / step + 1  # frames spanned by each segment
    counts = _segment_counts(lengths, n, step)
    expected = np.degrees(np.average(frames * omega / lengths, weights=counts)) * 100
    assert r_err == pytest.approx(expected, rel=1e-6)


def test_kitti_error_matches_kiss_icp_up_to_its_pi() -> None:
    kiss_metrics = pytest.importorskip("kiss_icp.metrics")
    rng = np.random.default_rng(5)
    n = 1500
    gt = _compose_steps(_se3((0, 0, 0.002), (1.0, 0, 0)), n)
    noise = [
        _se3(rng.normal(scale=0.002, size=3), rng.normal(scale=0.02, size=3)) for _ in range(n)
    ]
    est = np.stack([gt[i] @ noise[i] for i in range(n)])
    t_err, r_err = kitti_relative_error(est, gt)
    kiss_t, kiss_r = kiss_metrics.sequence_error(list(gt), list(est))
    assert t_err == pytest.approx(kiss_t, rel=1e-4)
    # KISS-ICP reports deg/m computed with 180/3.14: a real difference of 0.05 %.
    assert r_err == pytest.approx(kiss_r * 100 * 3.14 / np.pi, rel=1e-4)
    assert r_err != pytest.approx(kiss_r * 100, rel=1e-4)


def test_kitti_error_of_a_short_trajectory_only_with_our_lengths() -> None:
    kiss_metrics = pytest.importorskip("kiss_icp.metrics")
    gt = _straight_line(100, 0.5)  # 49.5 m: no 100 m segment
    est = _straight_line(100, 0.505)
    assert all(math.isnan(x) for x in kiss_metrics.sequence_error(list(gt), list(est)))
    t_err, _ = kitti_relative_error(est, gt, lengths_m=(10.0,))
    assert t_err == pytest.approx(100 * 10.5 * 0.01 / 10.0, rel=1e-9)


def test_kitti_error_is_nan_on_a_short_trajectory_unless_lengths_are_given() -> None:
    gt = _straight_line(100, 0.5)  # 49.5 m
    est = _straight_line(100, 0.505)
    t_err, r_err = kitti_relative_error(est, gt)
    assert math.isnan(t_err) and math.isnan(r_err)
    t_short, _ = kitti_relative_error(est, gt, lengths_m=(10.0, 20.0))
    lengths = np.array([10.0, 20.0])
    expected = np.average((lengths + 0.5) / lengths, weights=_segment_counts(lengths, 100, 0.5))
    assert t_short == pytest.approx(expected, rel=1e-9)


def test_trajectory_metrics_bundle() -> None:
    gt = _random_trajectory(60, seed=4)
    result = trajectory_metrics(_se3((0, 0, 1), (1, 2, 3)) @ gt, gt, kitti_lengths_m=(10.0,))
    assert result.ate_rmse_m < 1e-9 and result.rpe_trans_rmse_m < 1e-9
    assert result.kitti_t_err_percent < 1e-7
    assert result.num_poses == 60 and result.length_m > 50
    assert set(result.as_dict()) >= {"ate_rmse_m", "kitti_t_err_percent", "length_m"}
    assert result.unaligned_rmse_m < 1e-9 and result.unaligned_tilt_mean_deg < 1e-6


def _turned_after(gt: np.ndarray, first: int, rotvec) -> np.ndarray:
    """``gt`` with every pose from ``first`` on turned by ``rotvec`` about the pose before it:
    an attitude step that stays."""
    pivot = gt[first - 1]
    turn = pivot @ _se3(rotvec) @ np.linalg.inv(pivot)
    est = gt.copy()
    est[first:] = turn @ gt[first:]
    return est


def test_an_attitude_step_that_stays_shows_unaligned_only() -> None:
    gt = _straight_line(100, 1.0)
    yawed = _turned_after(gt, 10, (0.0, 0.0, math.radians(0.5)))
    tilted = _turned_after(gt, 10, (0.0, math.radians(0.5), 0.0))
    for est, yaw, tilt in ((yawed, 0.45, 0.0), (tilted, 0.0, 0.45)):
        error = unaligned_error(est, gt)
        assert error.yaw_mean_abs_deg == pytest.approx(yaw, abs=1e-6)
        assert error.tilt_mean_deg == pytest.approx(tilt, abs=1e-6)
        # 0.5 deg over up to 89 m: the positions drift off by up to 0.78 m...
        assert 0.35 < error.position_rmse_m < 0.5
        # ... which an alignment spreads over the whole line
        assert ate_rmse(est, gt) < 0.6 * error.position_rmse_m


def test_unaligned_errors_ignore_the_world_frame_and_take_the_up_axis() -> None:
    gt = _random_trajectory(60, seed=5)
    moved = _se3((0.3, -0.2, 1.0), (5.0, 1.0, -2.0)) @ gt
    assert unaligned_error(moved, gt).position_rmse_m < 1e-9
    # a camera (y down): a turn about its y axis is a yaw, about its x axis a tilt
    turned = _turned_after(gt, 1, (0.0, math.radians(1.0), 0.0))
    camera = unaligned_error(turned, gt, CAMERA_UP)
    assert camera.tilt_mean_deg < 1e-6 and camera.yaw_mean_abs_deg > 0.9


# --- trajectory files -----------------------------------------------------------------------


def test_kitti_and_tum_files_round_trip(tmp_path: Path) -> None:
    poses = _random_trajectory(25, seed=6)
    stamps = 1.3e9 + np.arange(25) * 0.1
    write_kitti(tmp_path / "a.kitti.txt", poses)
    write_tum(tmp_path / "a.tum.txt", poses, stamps)
    np.testing.assert_allclose(read_kitti(tmp_path / "a.kitti.txt"), poses, atol=1e-6)
    read_stamps, read_poses = read_tum(tmp_path / "a.tum.txt")
    np.testing.assert_allclose(read_poses, poses, atol=1e-6)
    np.testing.assert_allclose(read_stamps, stamps, atol=1e-6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.kitti.txt", "a.tum.txt"]
    first = (tmp_path / "a.tum.txt").read_text().splitlines()[1].split()
    assert len(first) == 8


def test_reads_the_real_kitti_ground_truth() -> None:
    path = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti" / "poses"
    if not (path / "00.txt").is_file():
        pytest.skip(f"real KITTI poses not found under {path}")
    poses = read_kitti(path / "00.txt")
    assert poses.shape == (4541, 4, 4)
    R = poses[:, :3, :3]
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.tile(np.eye(3), (4541, 1, 1)), atol=1e-4
    )


def test_malformed_trajectory_files_name_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3\n")
    with pytest.raises(DatasetError, match=r"bad\.txt:1: expected 12"):
        read_kitti(bad)
    with pytest.raises(DatasetError, match="not found"):
        read_tum(tmp_path / "missing.txt")
    bad.write_text("# only a comment\n")
    with pytest.raises(DatasetError, match="no poses"):
        read_tum(bad)


# --- mesh metrics ---------------------------------------------------------------------------

SAMPLES = 20_000


def test_identical_meshes_score_perfectly() -> None:
    mesh = trimesh.creation.icosphere(subdivisions=3)
    result = mesh_metrics(mesh, mesh.copy(), num_samples=SAMPLES)
    # Not exactly 0: a candidate triangle may be a neighbour of the true one (micrometres).
    assert result.accuracy_m < 2e-5 and result.completion_m < 2e-5
    assert result.completion_ratio == 1.0 and result.f_score == 1.0


def test_concentric_spheres_one_centimetre_apart() -> None:
    gt = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    pred = trimesh.creation.icosphere(subdivisions=5, radius=1.01)
    result = mesh_metrics(pred, gt, num_samples=SAMPLES)
    # Tessellation makes the gap vary slightly around 1 cm.
    assert result.accuracy_m == pytest.approx(0.01, abs=5e-4)
    assert result.completion_m == pytest.approx(0.01, abs=5e-4)
    assert mesh_metrics(pred, gt, num_samples=SAMPLES, threshold_m=0.005).completion_ratio == 0
    assert mesh_metrics(pred, gt, num_samples=SAMPLES, threshold_m=0.02).completion_ratio == 1


def test_plane_shifted_along_its_normal() -> None:
    square = trimesh.Trimesh(
        vertices=[[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], faces=[[0, 1, 2], [0, 2, 3]]
    )
    gt = square.subdivide().subdivide()
    pred = gt.copy()
    pred.apply_translation((0, 0, 0.01))
    result = mesh_metrics(pred, gt, num_samples=SAMPLES)
    assert result.accuracy_m == pytest.approx(0.01, abs=1e-9)
    assert result.completion_m == pytest.approx(0.01, abs=1e-9)


def test_half_reconstruction_and_face_mask() -> None:
    gt = trimesh.creation.box(extents=(2.0, 2.0, 2.0)).subdivide().subdivide()
    keep = gt.face_normals[:, 0] > 0.9  # the +x side, 1/6 of the area
    pred = gt.submesh([np.flatnonzero(keep)], append=True)
    result = mesh_metrics(pred, gt, num_samples=SAMPLES)
    assert result.accuracy_m < 2e-5 and result.precision_ratio == 1.0
    # The +x side plus 5 cm strips of its four neighbours: (4 + 4 * 2 * 0.05) / 24 of the area.
    assert result.completion_ratio == pytest.approx(4.4 / 24, abs=0.01)
    masked = mesh_metrics(pred, gt, num_samples=SAMPLES, gt_face_mask=keep)
    assert masked.completion_ratio == 1.0 and masked.completion_m < 2e-5


def test_empty_prediction_gives_infinite_distances() -> None:
    gt = trimesh.creation.box()
    result = mesh_metrics(trimesh.Trimesh(), gt, num_samples=1000)
    assert math.isinf(result.accuracy_m) and math.isinf(result.completion_m)
    assert result.completion_ratio == 0.0 and result.num_pred_faces == 0
    with pytest.raises(ValueError, match="ground-truth mesh has no faces"):
        mesh_metrics(gt, trimesh.Trimesh())


def test_surface_distance_is_exact_for_points_off_a_box() -> None:
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    points = np.array([[0, 0, 1.3], [1.5, 0, 0], [2.0, 2.0, 1.0], [0, 0, 0]])
    expected = [0.3, 0.5, math.sqrt(2), 1.0]
    np.testing.assert_allclose(surface_distances(points, box, num_reference_samples=5000), expected)


def test_visible_face_mask_keeps_only_faces_in_front_of_the_camera() -> None:
    mesh = trimesh.creation.box(extents=(2.0, 2.0, 2.0)).subdivide()
    # Camera at the origin of the box looking along +z (OpenCV convention).
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    mask = visible_face_mask(mesh, np.eye(4)[None], K, 100, 100)
    assert mask.any()
    assert np.all(mesh.triangles_center[mask, 2] > 0.99)
