"""The whole back-end on short generated loops: loop closure, pose graph, remapping.

The odometry is the ground truth with a constant per-frame bias accumulated on top (a stand-in for
a drifting front-end), so that loop closure has a known drift to remove; everything downstream
(keyframing, neural map, loop detection and verification, pose graph, remapping) is the real code.
"""

from __future__ import annotations

import numpy as np
import pytest

from frontends.frame import Frame
from frontends.odometry.ground_truth import GroundTruthOdometry
from frontends.sources import make_source
from slam.algorithm.loops.registry import make_loop_detector
from slam.algorithm.merge.session import session_from_pipeline
from slam.assembly.builders import build_map
from slam.evaluation.metrics.mesh import mesh_metrics
from slam.evaluation.metrics.trajectory import ate_per_axis_rmse, ate_rmse
from tests.pipeline_setups import (
    ROOM,
    STREET,
    DriftingOdometry,
    FalseLoopInjector,
    room_config,
    room_odometry,
    run,
    street_config,
)


@pytest.fixture(scope="module")
def room():
    """Every second frame of the generated room lap (the drift does not need them all)."""
    return make_source(
        "generated",
        **ROOM,
        frames=slice(None, None, 2),
        loader_options={"depth_options": {"stride": 2}},
    )


@pytest.fixture(scope="module")
def room_run(room):
    cfg = room_config(max_map_points=20000)
    return cfg, run(cfg, room, room_odometry())


def test_rgbd_loop_is_closed_and_lowers_ate(room, room_run):
    _, pipeline = room_run
    kept = [c for c in pipeline.loop_candidates if c.accepted and c.graph_inlier]
    assert kept, [c.reason for c in pipeline.loop_candidates]
    gt = room.gt_poses
    ate_odometry = ate_rmse(pipeline.frames.odometry_poses(), gt)
    ate_slam = ate_rmse(pipeline.slam_poses(), gt)
    assert ate_slam < 0.5 * ate_odometry, (ate_slam, ate_odometry)
    # The loop moved the map: submaps were remapped from their original encodings.
    assert any(e.num_moved for e in pipeline.remapper.events)
    assert all(s.fused for s in pipeline.submaps.values())


def test_frames_follow_the_graphs_odometry_between_anchors(room_run):
    """The track's odometry between consecutive anchors is the pose graph's odometry factor,
    and the run's session places every frame as the run did; after the loop moved the anchors
    the frames in between moved with both of their anchors, not only with their own."""
    _, pipeline = room_run
    successors = pipeline.frames.successors()
    edges = pipeline.graph.odometry_edges()
    assert len(edges) == len(successors) >= 5
    for i, j, T_Ai_Aj, _ in edges:
        assert successors[i][0] == j
        np.testing.assert_allclose(successors[i][1], T_Ai_Aj, atol=1e-9)
    session = session_from_pipeline(pipeline, {"sensor": "rgbd"}, None)
    np.testing.assert_allclose(session.frame_poses(), pipeline.slam_poses(), atol=1e-9)
    rigid = pipeline.frames.slam_poses(pipeline.view.poses(), follow_next_anchor=False)
    moved = np.linalg.norm(pipeline.slam_poses()[:, :3, 3] - rigid[:, :3, 3], axis=1)
    assert moved.max() > 1e-4, moved.max()


def test_finish_releases_the_kept_keyframes_but_not_the_descriptors(room_run):
    """After the last submap no loop can use the kept keyframes (images, features, clouds): the
    final mesh runs without them; the place descriptors stay for the session."""
    _, pipeline = room_run
    detector = pipeline.loop_detector
    assert detector._features == {}
    assert sorted(detector.descriptors) == sorted(pipeline.records)


def test_remapped_map_matches_a_map_encoded_at_the_final_poses(room_run):
    cfg, pipeline = room_run
    scratch = build_map(cfg)
    final = pipeline.graph.poses()
    for submap_id, record in pipeline.records.items():
        held = pipeline.submaps[submap_id].T_W_A
        assert np.linalg.norm(held[:3, 3] - final[submap_id][:3, 3]) <= 0.002
        scratch.fuse(scratch.encode(submap_id, record.points_A, record.normals_A, final[submap_id]))
    remapped_mesh = pipeline.map.extract_mesh()
    scratch_mesh = scratch.extract_mesh()
    assert len(remapped_mesh.faces) > 1000 and len(scratch_mesh.faces) > 1000
    distance = mesh_metrics(remapped_mesh, scratch_mesh, num_samples=30_000)
    assert distance.accuracy_m < 0.01, distance
    assert distance.completion_m < 0.01, distance


def test_a_false_loop_edge_does_not_spoil_the_trajectory(room, room_run):
    _, clean = room_run
    cfg = room_config(max_map_points=1000)
    detector = FalseLoopInjector(
        make_loop_detector(cfg.loop_closure, "rgbd"), at_submap=8, wrong_by_m=2.0
    )
    corrupted = run(cfg, room, room_odometry(), detector)
    injected = [c for c in corrupted.loop_candidates if c.detector == "injected"]
    assert len(injected) == 1 and injected[0].graph_inlier is False
    gt = room.gt_poses
    ate_clean = ate_rmse(clean.slam_poses(), gt)
    ate_corrupted = ate_rmse(corrupted.slam_poses(), gt)
    assert ate_corrupted <= 1.1 * ate_clean + 1e-3, (ate_corrupted, ate_clean)


def test_lidar_loop_is_closed_and_lowers_ate():
    street = make_source("generated", **STREET)
    cfg = street_config()
    odometry = DriftingOdometry(yaw_deg_per_frame=0.015, scale=1.0, up_axis=2)
    pipeline = run(cfg, street, odometry)
    kept = [c for c in pipeline.loop_candidates if c.accepted and c.graph_inlier]
    assert kept, [c.reason for c in pipeline.loop_candidates]
    gt = street.gt_poses
    ate_odometry = ate_rmse(pipeline.frames.odometry_poses(), gt)
    ate_slam = ate_rmse(pipeline.slam_poses(), gt)
    assert ate_slam < 0.5 * ate_odometry, (ate_slam, ate_odometry)
    assert any(e.num_moved for e in pipeline.remapper.events)


def test_gravity_factors_take_out_a_pitch_drift():
    """A steady nose-up bias bends the lap into a bowl that its own loop agrees with; the up
    directions measured on the anchor scans' walls flatten it."""
    street = make_source("generated", **STREET)
    gt = street.gt_poses
    runs = {}
    for enabled in (False, True):
        cfg = street_config()
        cfg.pose_graph.gravity.enabled = enabled
        # what generated walls measure (1-2 mrad); the default is looser, tuned on longer runs
        cfg.pose_graph.gravity.sigma_rad = 0.005
        odometry = DriftingOdometry(0.0, 1.0, up_axis=2, pitch_deg_per_frame=0.1)
        pipeline = run(cfg, street, odometry)
        runs[enabled] = (
            ate_per_axis_rmse(pipeline.slam_poses(), gt),
            len(pipeline.graph.up_measurements),
            len(pipeline.graph.node_ids),
        )
    (xyz_off, factors_off, _), (xyz_on, factors_on, anchors) = runs[False], runs[True]
    assert factors_off == 0 and factors_on >= anchors - 1, (factors_on, anchors)
    assert xyz_off[2] > 0.1, xyz_off
    assert xyz_on[2] < 0.5 * xyz_off[2], (xyz_on, xyz_off)
    assert np.hypot(*xyz_on[:2]) <= 1.2 * np.hypot(*xyz_off[:2]) + 0.02, (xyz_on, xyz_off)


def test_ground_truth_odometry_keeps_the_true_poses():
    """Exact poses get no up-direction factor: one would only tilt them by its own error."""
    street = make_source("generated", **STREET, frames=slice(0, 40))
    cfg = street_config()
    cfg.pose_graph.gravity.enabled = True
    pipeline = run(cfg, street, GroundTruthOdometry())
    assert len(pipeline.graph.node_ids) >= 2
    assert not pipeline.graph.up_measurements
    error_m = np.linalg.norm(pipeline.slam_poses()[:, :3, 3] - street.gt_poses[:, :3, 3], axis=1)
    assert error_m.max() < 1e-3, error_m.max()


def test_frames_wait_for_the_submap_worker_without_their_images() -> None:
    """The submap worker absorbs points and normals only; a queued RGB-D frame drops its images
    and colours and shares the rest (the same arrays, so the same submap points)."""
    rng = np.random.default_rng(0)
    points, normals = rng.normal(size=(100, 3)), rng.normal(size=(100, 3))
    frame = Frame(
        index=3,
        timestamp=0.1,
        points=points,
        normals=normals,
        colors=np.zeros((100, 3), np.uint8),
        depth=np.ones((48, 64), np.float32),
        rgb=np.zeros((48, 64, 3), np.uint8),
    )
    queued = frame.without_images()
    assert queued.depth is None and queued.rgb is None and queued.colors is None
    assert queued.points is points and queued.normals is normals
    assert (queued.index, queued.timestamp) == (3, 0.1)
    lidar = Frame(index=0, timestamp=0.0, points=points)
    assert lidar.without_images() is lidar
