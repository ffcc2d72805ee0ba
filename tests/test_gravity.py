"""Up direction from vertical structure, and the pose graph's gravity factors (fast, no data)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.algorithm.graph.config import GravityConfig, PoseGraphConfig
from slam.algorithm.graph.gravity import UpMeasurement, estimate_up
from slam.algorithm.graph.pose_graph import PoseGraph
from slam.algorithm.merge.session import Edge, SessionRecord

CFG = GravityConfig(enabled=True)


def scene_normals(
    R_A_W: np.ndarray,
    rng: np.random.Generator,
    wall_noise_rad: float,
    headings: np.ndarray,
    clutter: int = 300,
) -> np.ndarray:
    """Unit normals seen from an anchor whose rotation to the world is ``R_A_W``: walls facing
    ``headings`` (radians, world), a sloped ground and ``clutter`` random normals."""
    walls = np.stack([np.cos(headings), np.sin(headings), np.zeros_like(headings)], axis=1)
    walls = walls + rng.normal(0, wall_noise_rad, walls.shape)
    slope = np.deg2rad(2.0)
    ground = np.tile([np.sin(slope), 0.0, np.cos(slope)], (400, 1)) + rng.normal(0, 0.01, (400, 3))
    normals = np.concatenate([walls, ground, rng.normal(0, 1, (clutter, 3))])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return normals @ R_A_W.T


def tilted(rotvec: list[float]) -> np.ndarray:
    return Rotation.from_rotvec(rotvec).as_matrix()


def test_up_is_recovered_from_noise_free_walls():
    rng = np.random.default_rng(0)
    R_W_A = tilted([0.03, -0.02, 0.7])
    normals = scene_normals(R_W_A.T, rng, 0.0, rng.uniform(0, 2 * np.pi, 2000), clutter=0)
    measurement = estimate_up(normals, np.array([0.0, 0.0, 1.0]), CFG)
    assert measurement is not None
    up_true_A = R_W_A.T @ [0.0, 0.0, 1.0]
    assert np.linalg.norm(measurement.up_A - up_true_A) < 1e-6
    # walls facing every way inform both tilt axes fully and the heading not at all
    values = np.linalg.eigvalsh(measurement.information_A)
    assert values[0] == pytest.approx(0.0, abs=1e-6)
    assert values[1] > 0.8 / CFG.sigma_rad**2
    assert abs(up_true_A @ measurement.information_A @ up_true_A) < 1e-6


def test_up_from_noisy_walls_is_within_a_milliradian():
    rng = np.random.default_rng(1)
    R_W_A = tilted([-0.04, 0.025, 2.0])
    normals = scene_normals(R_W_A.T, rng, 0.02, rng.uniform(0, 2 * np.pi, 3000))
    measurement = estimate_up(normals, np.array([0.0, 0.0, 1.0]), CFG)
    assert measurement is not None
    error = np.arccos(np.clip(measurement.up_A @ (R_W_A.T @ [0.0, 0.0, 1.0]), -1, 1))
    assert error < 1e-3


def test_walls_facing_one_way_inform_one_tilt_axis():
    rng = np.random.default_rng(2)
    headings = np.where(rng.random(1500) < 0.5, np.pi / 2, -np.pi / 2)  # normals along +-y
    measurement = estimate_up(scene_normals(np.eye(3), rng, 0.0, headings), np.eye(3)[2], CFG)
    assert measurement is not None
    information = measurement.information_A
    # a tilt about x moves up towards y, which those walls see; a tilt about y they do not
    assert information[0, 0] > 0.8 / CFG.sigma_rad**2
    assert information[1, 1] < 1e-5 * information[0, 0]


def test_no_walls_no_measurement():
    rng = np.random.default_rng(3)
    ground_only = scene_normals(np.eye(3), rng, 0.0, np.zeros(0))[:400]
    assert estimate_up(ground_only, np.eye(3)[2], CFG) is None


def curved_circle(num: int, bias_rad: float, radius_m: float = 20.0):
    """Level anchors on a circle (the truth) and an odometry whose every step pitches the nose
    up by ``bias_rad``: a drift of constant curvature, which closes around the loop."""
    gt = np.tile(np.eye(4), (num, 1, 1))
    for k in range(num):
        angle = 2 * np.pi * k / num
        gt[k, :3, :3] = Rotation.from_euler("z", angle + np.pi / 2).as_matrix()
        gt[k, :3, 3] = [radius_m * np.cos(angle), radius_m * np.sin(angle), 0.0]
    bias = np.eye(4)
    bias[:3, :3] = tilted([0.0, -bias_rad, 0.0])  # about the body's left axis: nose up
    odometry = [gt[0]]
    for k in range(1, num):
        odometry.append(odometry[-1] @ np.linalg.inv(gt[k - 1]) @ gt[k] @ bias)
    return gt, np.array(odometry)


def level_measurement(R_W_A_true: np.ndarray, sigma_rad: float = 0.003) -> UpMeasurement:
    """The true up direction of an anchor, informing both tilt axes with ``sigma_rad``."""
    up_A = R_W_A_true.T @ [0.0, 0.0, 1.0]
    basis = np.linalg.svd(up_A[None, :])[2][1:].T
    return UpMeasurement(up_A, basis @ basis.T / sigma_rad**2, 1000)


@pytest.mark.parametrize("online_gnc", [True, False])
def test_gravity_removes_the_curvature_that_a_loop_cannot_see(online_gnc):
    gt, odometry = curved_circle(36, bias_rad=0.004)
    cfg = PoseGraphConfig(online_gnc=online_gnc)
    results = {}
    for with_gravity in (False, True):
        graph = PoseGraph(cfg)
        for k, T in enumerate(odometry):
            graph.add_anchor(k, T)
            if with_gravity:
                graph.add_gravity(k, level_measurement(gt[k, :3, :3]))
        edge = graph.add_loop(len(gt) - 1, 0, np.linalg.inv(gt[-1]) @ gt[0])
        assert edge.inlier  # the curved odometry agrees with the loop
        poses = graph.optimize_batch()
        results[with_gravity] = max(abs(T[2, 3]) for T in poses.values())
    # the odometry alone peaks at 2 R^2 bias / step (0.9 m here), loop or not
    assert results[False] > 0.5
    assert results[True] < 0.01 * results[False], results


def test_an_attitude_step_between_the_first_anchors_does_not_tilt_the_rest():
    """The odometry rolls by 0.3 deg between the first two anchors of a straight, level drive
    and is exact after that. The first anchor's scan sees the true up: the gravity frame keeps
    it, so the factors of the later anchors take the step back out (a free gravity frame
    followed the later anchors and kept about half of the step in every one of them)."""
    step_rad, num = np.deg2rad(0.3), 12
    gt = np.tile(np.eye(4), (num, 1, 1))
    gt[:, 0, 3] = 30.0 * np.arange(num)
    odometry = gt.copy()
    odometry[1:, :3, :3] = tilted([step_rad, 0.0, 0.0])
    cfg = PoseGraphConfig(
        odometry_rotation_sigma_rad=0.002,
        odometry_rotation_sigma_rad_per_m=0.0003,
        gravity=GravityConfig(enabled=True, sigma_rad=0.01),
    )
    graph = PoseGraph(cfg)
    for k in range(num):
        graph.add_anchor(k, odometry[k])
        graph.add_gravity(k, level_measurement(gt[k, :3, :3], sigma_rad=cfg.gravity.sigma_rad))
    poses = graph.optimize_batch()
    tilts = [np.arccos(np.clip(poses[k][2, 2], -1.0, 1.0)) for k in range(1, num)]
    assert np.mean(tilts) < 0.2 * step_rad, np.degrees(tilts)


@pytest.mark.parametrize("measured_before_reframe", [True, False])
def test_a_reframe_onto_map_priors_frees_the_gravity_frame(measured_before_reframe):
    """Priors from a stored map place the graph after a reframe with ``prior_sigmas``: the
    gravity frame's tilt then follows them instead of holding the first measurement, whether
    that measurement came before the reframe or after it."""
    gt, odometry = curved_circle(8, bias_rad=0.0)
    graph = PoseGraph(PoseGraphConfig())
    for k, T in enumerate(odometry):
        graph.add_anchor(k, T)
        if measured_before_reframe:
            graph.add_gravity(k, level_measurement(gt[k, :3, :3]))
    T_Map_W = np.eye(4)
    T_Map_W[:3, :3] = tilted([0.02, 0.0, 0.0])  # the stored map is rolled by 20 mrad
    graph.reframe(np.eye(4), prior_sigmas=(1.0, 10.0))
    if not measured_before_reframe:
        for k in range(len(gt)):
            graph.add_gravity(k, level_measurement(gt[k, :3, :3]))
    for k in range(len(gt)):
        graph.add_map_prior(k, T_Map_W @ gt[k], np.eye(6) * 1e-6)
    up_W = T_Map_W[:3, :3] @ [0.0, 0.0, 1.0]
    assert np.allclose(graph.pose(3)[:3, :3] @ graph.up_in(3), up_W, atol=1e-3)


def test_up_follows_the_graph_through_a_reframe():
    gt, odometry = curved_circle(8, bias_rad=0.0)
    graph = PoseGraph(PoseGraphConfig())
    for k, T in enumerate(odometry):
        graph.add_anchor(k, T)
        graph.add_gravity(k, level_measurement(gt[k, :3, :3]))
    up_before = graph.up_in(5)
    T_New_W = np.eye(4)
    T_New_W[:3, :3] = tilted([0.2, -0.1, 1.0])
    T_New_W[:3, 3] = [3.0, -2.0, 1.0]
    graph.reframe(T_New_W)
    assert np.allclose(graph.up_in(5), up_before, atol=1e-9)
    assert np.allclose(graph.pose(5), T_New_W @ gt[5], atol=1e-6)
    assert len(graph.up_measurements) == 8


def test_gravity_on_an_unknown_anchor_is_refused():
    graph = PoseGraph(PoseGraphConfig())
    graph.add_anchor(0, np.eye(4))
    with pytest.raises(KeyError, match="anchor 3"):
        graph.add_gravity(3, level_measurement(np.eye(3)))


def _session_of(graph: PoseGraph, with_up: bool) -> SessionRecord:
    nodes = np.array(graph.node_ids)
    return SessionRecord(
        setup={},
        node_ids=nodes,
        T_W_A=np.array([graph.pose(int(n)) for n in nodes]),
        odometry=[Edge(i, j, T, cov) for i, j, T, cov in graph.odometry_edges()],
        loops=[],
        frame_submap=np.zeros(0, np.int64),
        frame_T_A_S=np.zeros((0, 4, 4)),
        timestamps=np.zeros(0),
        descriptors={},
        up=dict(graph.up_measurements) if with_up else {},
    )


def test_a_merge_keeps_the_runs_gravity_factors():
    """Two runs (the two halves of a curved lap), merged by the loops where they meet: with
    their stored up directions the merged lap is flat, without them it keeps the bowl."""
    from slam.algorithm.merge.config import MergeConfig
    from slam.algorithm.merge.merge import InterLoop, SessionInput, _Ids, _solve

    gt, odometry = curved_circle(36, bias_rad=0.004)
    graphs = []
    for part in (range(0, 18), range(18, 36)):
        graph = PoseGraph(PoseGraphConfig())
        for k in part:
            graph.add_anchor(k, odometry[k])
            graph.add_gravity(k, level_measurement(gt[k, :3, :3]))
        graphs.append(graph)
    covariance = np.diag([1e-6] * 3 + [1e-4] * 3)
    heights = {}
    for with_up in (False, True):
        inputs = [
            SessionInput(n, _session_of(g, with_up), []) for n, g in zip("ab", graphs, strict=True)
        ]
        loops = [
            InterLoop(i, j, 0, 1, True, "", np.linalg.inv(gt[i]) @ gt[j], covariance=covariance)
            for i, j in ((17, 18), (0, 35))
        ]
        poses, _ = _solve(inputs, _Ids(inputs), loops, [np.eye(4), np.eye(4)], MergeConfig())
        heights[with_up] = max(abs(T[2, 3]) for T in poses.values())
    assert heights[False] > 0.5
    assert heights[True] < 0.01 * heights[False], heights
