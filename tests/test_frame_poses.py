"""Frame poses between two anchors: the pose graph's correction at the next anchor is spread over
the frames in between, by path travelled, and nothing moves where the graph agrees with the
odometry."""

from __future__ import annotations

import numpy as np

from common.geometry import rotation_angle_rad, so3_exp
from slam.algorithm.frame_track import FrameTrack, frame_poses


def _pose(rotvec, translation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.asarray(rotvec, dtype=np.float64))
    T[:3, 3] = translation
    return T


def _drive(frames: int = 60, pitch_drift_rad: float = 2e-4):
    """A straight 1 m-per-frame drive that climbs and turns, and an odometry whose pitch drifts
    by ``pitch_drift_rad`` a frame; submaps of 20 frames, each anchored at its first frame."""
    truth, odometry = [], []
    T_true, T_odo = np.eye(4), np.eye(4)
    for _ in range(frames):
        truth.append(T_true.copy())
        odometry.append(T_odo.copy())
        step = _pose([0.0, 0.01, 0.02], [1.0, 0.0, 0.05])
        T_true = T_true @ step
        T_odo = T_odo @ _pose([0.0, pitch_drift_rad, 0.0], [0.0, 0.0, 0.0]) @ step
    return np.array(truth), np.array(odometry)


def _track(odometry: np.ndarray, frames_per_submap: int = 20) -> FrameTrack:
    track = FrameTrack()
    for i, T_W_S in enumerate(odometry):
        submap = i // frames_per_submap
        T_W_A = odometry[submap * frames_per_submap]
        track.add(submap, np.linalg.inv(T_W_A) @ T_W_S, T_W_S, float(i), None)
    return track


def _tilt_deg(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    up = np.array([0.0, 0.0, 1.0])
    turned = est[:, :3, :3] @ np.swapaxes(truth[:, :3, :3], 1, 2) @ up
    return np.degrees(np.arccos(np.clip(turned @ up, -1.0, 1.0)))


def test_frames_follow_both_anchors_where_the_graph_corrected_the_odometry():
    truth, odometry = _drive()
    track = _track(odometry)
    anchors_true = {s: truth[20 * s] for s in range(3)}  # a graph that found every anchor
    rigid = track.slam_poses(anchors_true, follow_next_anchor=False)
    followed = track.slam_poses(anchors_true)
    # rigid frames keep the odometry's drift since their anchor; the last submap has no next
    # anchor and stays rigid either way
    np.testing.assert_allclose(followed[40:], rigid[40:], atol=1e-12)
    np.testing.assert_allclose(followed[[0, 20]], truth[[0, 20]], atol=1e-9)
    tilt_rigid, tilt_followed = (
        _tilt_deg(rigid[:40], truth[:40]),
        _tilt_deg(followed[:40], truth[:40]),
    )
    assert tilt_rigid.max() > 0.2  # 19 frames of 2e-4 rad
    assert tilt_followed.max() < 0.1 * tilt_rigid.max(), (tilt_followed.max(), tilt_rigid.max())
    position_rigid = np.linalg.norm(rigid[:40, :3, 3] - truth[:40, :3, 3], axis=1)
    position_followed = np.linalg.norm(followed[:40, :3, 3] - truth[:40, :3, 3], axis=1)
    # the drift's position error grows with the square of the path; a linear share of the end
    # gap leaves at most a quarter of it, in the middle
    assert position_followed.max() < 0.3 * position_rigid.max()


def test_submaps_registered_to_a_stored_map_keep_their_frames_rigid():
    """A registration places a submap's frames rigidly at their best fit: they stay there."""
    truth, odometry = _drive()
    track = _track(odometry)
    anchors = {s: truth[20 * s] for s in range(3)}
    rigid = track.slam_poses(anchors, follow_next_anchor=False)
    kept = track.slam_poses(anchors, rigid={0})
    np.testing.assert_allclose(kept[:20], rigid[:20], atol=1e-12)
    np.testing.assert_allclose(kept[20:], track.slam_poses(anchors)[20:], atol=1e-12)
    assert np.abs(kept[21:40] - rigid[21:40]).max() > 1e-4


def test_nothing_moves_where_the_graph_agrees_with_the_odometry():
    _, odometry = _drive()
    track = _track(odometry)
    successors = track.successors()
    assert sorted(successors) == [0, 1] and [j for j, _ in successors.values()] == [1, 2]
    # anchors placed exactly where the odometry puts them, in another world frame
    T_W_O = _pose([0.3, -0.2, 1.0], [5.0, -3.0, 2.0])
    anchors = {s: T_W_O @ odometry[20 * s] for s in range(3)}
    np.testing.assert_allclose(track.slam_poses(anchors), T_W_O @ odometry, atol=1e-9)


def test_a_frame_at_the_next_anchor_lands_on_it():
    rng = np.random.default_rng(4)
    T_A_B = _pose(rng.normal(size=3) * 0.1, [4.0, 1.0, 0.2])
    frame_T_A_S = np.array([np.eye(4), _pose([0, 0, 0.05], [2.0, 0.5, 0.1]), T_A_B, np.eye(4)])
    anchors = {
        1: _pose([0.0, 0.0, 0.3], [1.0, 2.0, 0.0]),
        2: _pose([0.02, -0.01, 0.4], [5.0, 3.0, 0.3]),
    }
    poses = frame_poses(np.array([1, 1, 1, 2]), frame_T_A_S, anchors, {1: (2, T_A_B)})
    np.testing.assert_allclose(poses[0], anchors[1], atol=1e-12)
    np.testing.assert_allclose(poses[2], anchors[2], atol=1e-9)  # travelled the whole way
    np.testing.assert_allclose(poses[3], anchors[2], atol=1e-12)
    # half-way along the path: between the two rigid placements, in rotation and position
    rigid_prev = anchors[1] @ frame_T_A_S[1]
    rigid_next = anchors[2] @ np.linalg.inv(T_A_B) @ frame_T_A_S[1]
    gap = rotation_angle_rad(rigid_prev[:3, :3].T @ rigid_next[:3, :3])
    to_prev = rotation_angle_rad(rigid_prev[:3, :3].T @ poses[1][:3, :3])
    to_next = rotation_angle_rad(rigid_next[:3, :3].T @ poses[1][:3, :3])
    assert 0 < to_prev < gap and 0 < to_next < gap
    np.testing.assert_allclose(to_prev + to_next, gap, rtol=1e-6)


def test_standing_still_spreads_the_correction_by_frame_count():
    T_A_B = np.eye(4)
    anchors = {0: np.eye(4), 1: _pose([0.0, 0.0, 0.01], [0.04, 0.0, 0.0])}
    poses = frame_poses(
        np.array([0, 0, 0, 0, 1]), np.tile(np.eye(4), (5, 1, 1)), anchors, {0: (1, T_A_B)}
    )
    np.testing.assert_allclose(poses[:4, 0, 3], [0.0, 0.01, 0.02, 0.03], atol=1e-12)
    assert np.isfinite(poses).all()
