"""Pose graph over submap anchors on synthetic trajectories with drift (fast, no data)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.algorithm.graph.config import PoseGraphConfig
from slam.algorithm.graph.pose_graph import PoseGraph


def circle(num: int, radius_m: float = 10.0) -> np.ndarray:
    """Anchors on a circle; the last one is back near the first."""
    poses = np.tile(np.eye(4), (num, 1, 1))
    for k in range(num):
        angle = 2 * np.pi * k / (num - 1)
        poses[k, :3, :3] = Rotation.from_euler("z", angle + np.pi / 2).as_matrix()
        poses[k, :3, 3] = [radius_m * np.cos(angle), radius_m * np.sin(angle), 0.0]
    poses[-1, :3, 3] += [0.3, 0.0, 0.0]
    return poses


def drifting(gt: np.ndarray, seed: int, sigma_t: float, sigma_r: float) -> np.ndarray:
    """Odometry: ground-truth increments with accumulating noise."""
    rng = np.random.default_rng(seed)
    odometry = [gt[0]]
    for k in range(1, len(gt)):
        step = np.linalg.inv(gt[k - 1]) @ gt[k]
        noise = np.eye(4)
        noise[:3, :3] = Rotation.from_rotvec(rng.normal(0, sigma_r, 3)).as_matrix()
        noise[:3, 3] = rng.normal(0, sigma_t, 3)
        odometry.append(odometry[-1] @ step @ noise)
    return np.array(odometry)


def ate(est: dict[int, np.ndarray] | np.ndarray, gt: np.ndarray) -> float:
    est = np.array(list(est.values())) if isinstance(est, dict) else est
    return float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=1))))


def relative(gt: np.ndarray, i: int, j: int) -> np.ndarray:
    return np.linalg.inv(gt[i]) @ gt[j]


def build(cfg: PoseGraphConfig, odometry: np.ndarray, loops, false_loops=()) -> PoseGraph:
    """Anchors in order; each loop is added as soon as both its anchors exist."""
    graph = PoseGraph(cfg)
    pending = [(i, j, T) for i, j, T in loops] + list(false_loops)
    for k, T in enumerate(odometry):
        graph.add_anchor(k, T)
        for i, j, T_ij in [p for p in pending if max(p[0], p[1]) == k]:
            graph.add_loop(i, j, T_ij)
    return graph


@pytest.fixture(scope="module")
def scenario():
    gt = circle(41)
    odometry = drifting(gt, seed=0, sigma_t=0.08, sigma_r=0.015)
    loops = [(0, 40, relative(gt, 0, 40)), (5, 25, relative(gt, 5, 25))]
    return gt, odometry, loops


@pytest.mark.parametrize("final", ["gnc", "lm"])
def test_loop_closure_reduces_ate(scenario, final):
    gt, odometry, loops = scenario
    graph = build(PoseGraphConfig(final_optimizer=final), odometry, loops)
    online = graph.poses()
    final_poses = graph.optimize_batch()
    assert ate(final_poses, gt) < 0.5 * ate(odometry, gt)
    assert ate(online, gt) < 0.7 * ate(odometry, gt)
    assert all(edge.inlier for edge in graph.loops)


def test_world_frame_is_the_first_anchor(scenario):
    _, odometry, loops = scenario
    graph = build(PoseGraphConfig(), odometry, loops)
    graph.optimize_batch()
    np.testing.assert_allclose(graph.pose(0), odometry[0], atol=1e-6)
    assert graph.node_ids == list(range(len(odometry)))


@pytest.mark.parametrize("online_gnc", [True, False])
def test_reframe_moves_the_whole_graph_rigidly(scenario, online_gnc):
    """A session relocalised in a stored map: reframing half way, then adding the rest of the
    anchors and loops, gives the graph built in the new frame from the start."""
    _, odometry, loops = scenario
    T_M_W = np.eye(4)
    T_M_W[:3, :3] = Rotation.from_euler("zyx", [130, -7, 4], degrees=True).as_matrix()
    T_M_W[:3, 3] = [12.0, -3.0, 0.5]
    cfg = PoseGraphConfig(online_gnc=online_gnc)
    half = 26  # after the first loop (5-25), before the second (0-40)
    graph = build(cfg, odometry[:half], [lp for lp in loops if max(lp[:2]) < half])
    before = graph.poses()
    graph.reframe(T_M_W)
    for node, T in before.items():
        np.testing.assert_allclose(graph.pose(node), T_M_W @ T, atol=1e-6)
    for k in range(half, len(odometry)):
        graph.add_anchor(k, odometry[k])
    graph.add_loop(*loops[0])
    expected = build(cfg, np.array([T_M_W @ T for T in odometry]), loops)
    reframed = graph.optimize_batch()
    for node, T in expected.optimize_batch().items():
        np.testing.assert_allclose(reframed[node], T, atol=1e-4)
    assert [e.inlier for e in graph.loops] == [e.inlier for e in expected.loops]


@pytest.mark.parametrize("online_gnc", [True, False])
def test_false_loop_is_rejected_or_down_weighted(scenario, online_gnc):
    gt, odometry, loops = scenario
    wrong = relative(gt, 10, 30)
    wrong[:3, 3] += [3.0, -2.0, 0.5]  # off by ~3.6 m
    cfg = PoseGraphConfig(online_gnc=online_gnc, final_optimizer="gnc" if online_gnc else "lm")
    clean = build(cfg, odometry, loops)
    corrupted = build(cfg, odometry, loops, false_loops=[(10, 30, wrong)])
    ate_clean = ate(clean.optimize_batch(), gt)
    ate_corrupted = ate(corrupted.optimize_batch(), gt)
    assert ate_corrupted <= 1.1 * ate_clean + 1e-3
    false_edge = next(e for e in corrupted.loops if (e.i, e.j) == (10, 30))
    assert false_edge.weight < 0.1
    assert not false_edge.inlier
    if online_gnc:
        assert all(e.inlier for e in corrupted.loops if (e.i, e.j) != (10, 30))


def test_true_loop_survives_large_drift():
    """GNC must keep a correct loop even when drift makes its first residual large."""
    gt = circle(41)
    odometry = drifting(gt, seed=3, sigma_t=0.05, sigma_r=0.03)
    graph = build(PoseGraphConfig(), odometry, [(0, 40, relative(gt, 0, 40))])
    assert graph.loops[0].inlier
    assert ate(graph.optimize_batch(), gt) < 0.6 * ate(odometry, gt)


def test_odometry_noise_grows_with_distance():
    graph = PoseGraph(PoseGraphConfig())
    near = graph.odometry_sigmas(1.0, 0.0)
    far = graph.odometry_sigmas(10.0, 0.5)
    assert np.all(far > near)


def test_bad_anchor_ids():
    graph = PoseGraph(PoseGraphConfig())
    graph.add_anchor(0, np.eye(4))
    with pytest.raises(ValueError):
        graph.add_anchor(0, np.eye(4))
    with pytest.raises(KeyError):
        graph.add_loop(0, 7, np.eye(4))


def test_estimate_after_a_loop_is_the_gnc_optimum(scenario):
    """The online estimate is the GNC solution itself, not a further step under another cost:
    Levenberg-Marquardt on the chain and the inlier loops does not move it, nor does the final
    GNC."""
    gt, odometry, loops = scenario
    wrong = relative(gt, 10, 30)
    wrong[:3, 3] += [3.0, -2.0, 0.5]
    graph = build(PoseGraphConfig(final_optimizer="gnc"), odometry, loops, [(10, 30, wrong)])
    # The last loop closes at the last anchor, so the estimate is the one right after GNC.
    online = graph.poses()
    values = gtsam.Values()
    for k, T in online.items():
        values.insert(k, gtsam.Pose3(T))
    polished = gtsam.LevenbergMarquardtOptimizer(graph._inlier_graph(), values).optimize()
    for k, T in online.items():
        np.testing.assert_allclose(polished.atPose3(k).matrix(), T, atol=1e-4)
    final = graph.optimize_batch()
    shift = max(np.linalg.norm(final[k][:3, 3] - online[k][:3, 3]) for k in online)
    assert shift < 1e-4


def test_final_lm_does_not_bring_back_rejected_loops(scenario):
    gt, odometry, loops = scenario
    wrong = relative(gt, 10, 30)
    wrong[:3, 3] += [3.0, -2.0, 0.5]
    cfg = PoseGraphConfig(final_optimizer="lm")
    clean = build(cfg, odometry, loops)
    corrupted = build(cfg, odometry, loops, [(10, 30, wrong)])
    ate_clean = ate(clean.optimize_batch(), gt)
    ate_corrupted = ate(corrupted.optimize_batch(), gt)
    false_edge = next(e for e in corrupted.loops if (e.i, e.j) == (10, 30))
    assert not false_edge.inlier
    assert abs(ate_corrupted - ate_clean) < 1e-4


def test_loop_covariance_sets_the_edge_weight(scenario):
    """An edge with a tight registration covariance pulls the graph; a loose one barely does."""
    gt, odometry, _ = scenario
    results = {}
    for sigma in (1e-3, 10.0):
        graph = PoseGraph(PoseGraphConfig(loop_min_sigma_m=0.0, loop_min_sigma_rad=0.0))
        for k, T in enumerate(odometry):
            graph.add_anchor(k, T)
        graph.add_loop(0, 40, relative(gt, 0, 40), covariance=np.eye(6) * sigma**2)
        T_0_40 = np.linalg.inv(graph.pose(0)) @ graph.pose(40)
        results[sigma] = np.linalg.norm(T_0_40[:3, 3] - relative(gt, 0, 40)[:3, 3])
    drift = np.linalg.norm(
        (np.linalg.inv(odometry[0]) @ odometry[40])[:3, 3] - relative(gt, 0, 40)[:3, 3]
    )
    assert results[1e-3] < 0.05 * drift
    assert results[10.0] > 0.9 * drift


@pytest.mark.parametrize("online_gnc", [True, False])
def test_map_priors_hold_the_anchors_to_a_stored_map(scenario, online_gnc):
    """A session localised in a stored map: a prior on every 4th anchor (its pose in the map's
    frame, as a registration to the stored map gives it) keeps the drifting chain on the
    truth, closer than the placement alone; a wrong prior (3.6 m off) does not pull it."""
    gt, odometry, _ = scenario
    cfg = PoseGraphConfig(online_gnc=online_gnc, final_optimizer="gnc" if online_gnc else "lm")
    placed_only = PoseGraph(cfg)
    anchored = PoseGraph(cfg)
    covariance = np.diag([1e-4] * 3 + [1e-3] * 3)
    for k, T in enumerate(odometry):
        for graph in (placed_only, anchored):
            graph.add_anchor(k, gt[0] @ np.linalg.inv(odometry[0]) @ T)
        if k % 4 == 3:
            anchored.add_map_prior(k, gt[k], covariance)
    wrong = gt[22].copy()
    wrong[:3, 3] += [3.0, -2.0, 0.5]
    edge = anchored.add_map_prior(22, wrong, covariance)
    final = anchored.optimize_batch()
    assert ate(final, gt) < 0.3 * ate(placed_only.optimize_batch(), gt)
    assert np.linalg.norm(final[22][:3, 3] - gt[22][:3, 3]) < 0.3
    assert len(anchored.map_priors) == 11 and anchored.loops == []
    if online_gnc:
        assert not edge.inlier  # GNC may drop one more where the odometry drifted fastest
        assert sum(e.inlier for e in anchored.map_priors if e is not edge) >= 9
    marginal = anchored.anchor_covariance(20)
    assert marginal.shape == (6, 6) and np.all(np.linalg.eigvalsh(marginal) > 0)
