"""Loop verification that aliasing cannot fool: a street whose facades repeat every 16 m.

Two submap clouds of the same stretch of a generated periodic street (real ray casting, real
KISS-ICP registration): a candidate whose ICP converges one period off passes every score gate
but is rejected as ambiguous, the true loop on the same street is accepted, and the pose graph's
chi-square gate rejects a correction far outside the odometry's accumulated uncertainty.
"""

from __future__ import annotations

import numpy as np
import pytest
from kiss_icp.voxelization import voxel_down_sample
from scipy.stats import chi2

from common.geometry import relative_motion, transform_points
from frontends.generate.lidar import LidarConfig, beam_directions, simulate_scan
from frontends.generate.raycast import Raycaster
from frontends.generate.street import PERIOD_M, street_scene
from slam.algorithm.graph.config import PoseGraphConfig
from slam.algorithm.graph.gtsam_poses import mahalanobis_distance2
from slam.algorithm.graph.pose_graph import PoseGraph
from slam.algorithm.loops.ambiguity import find_ambiguity
from slam.algorithm.loops.config import LidarLoopConfig
from slam.algorithm.loops.lidar_verify import IcpVerifier

LOOP_CONFIG = {"icp_max_correspondence_m": 1.5}  # configs/kitti.yaml


def _pose(x: float, y: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, 0.0]
    return T


@pytest.fixture(scope="module")
def periodic_pair():
    """Reference and query submap clouds (15 scans 2 m apart, 3-30 m, 0.5 m voxels) of the same
    stretch of a straight periodic street, the query 0.7 m ahead and 0.5 m to the side."""
    path = np.stack([np.linspace(-100, 300, 401), np.zeros(401), np.zeros(401)], axis=1)
    scene = street_scene(path, seed=0, style="periodic")
    raycaster = Raycaster(scene.mesh)
    lidar = LidarConfig(azimuth_steps=1024)
    directions = beam_directions(lidar)

    def submap(x0: float, y: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        rng = np.random.default_rng(seed)
        T_W_A = _pose(x0, y)
        parts = []
        for k in range(15):
            T_W_S = _pose(x0 + 2.0 * k, y)
            points, _ = simulate_scan(raycaster, scene, T_W_S, lidar, rng, directions)
            r = np.linalg.norm(points, axis=1)
            points = points[(r > 3.0) & (r < 30.0)]
            parts.append(transform_points(np.linalg.inv(T_W_A) @ T_W_S, points))
        return T_W_A, voxel_down_sample(np.concatenate(parts), 0.5)

    T_W_Ai, reference = submap(100.0, 0.0, seed=1)
    T_W_Aj, query = submap(100.7, 0.5, seed=2)
    return reference, query, np.linalg.inv(T_W_Ai) @ T_W_Aj


def _guess(T_true: np.ndarray, along_m: float) -> np.ndarray:
    guess = T_true.copy()
    guess[0, 3] += along_m
    return guess


def test_one_period_off_passes_the_score_gates_but_is_rejected_as_ambiguous(periodic_pair):
    reference, query, T_true = periodic_pair
    guess = _guess(T_true, PERIOD_M - 1.0)  # e.g. a drifted proximity guess
    unchecked = IcpVerifier(LidarLoopConfig(**LOOP_CONFIG, ambiguity_check=False))
    aliased = unchecked.verify(reference, query, guess, limit_correction=False)
    error_m, _ = relative_motion(T_true, aliased.T_ref_query)
    assert abs(error_m - PERIOD_M) < 1.0, "ICP should converge one period off"
    assert aliased.accepted, f"the score gates alone accept the aliased solution: {aliased.reason}"

    checked = IcpVerifier(LidarLoopConfig(**LOOP_CONFIG))
    result = checked.verify(reference, query, guess, limit_correction=False)
    assert not result.accepted
    assert result.reason.startswith("ambiguous"), result.reason
    assert result.scores["ambiguity_alternative_score"] > result.scores["ambiguity_score"]


def test_a_few_metres_along_the_street_passes_the_score_gates_but_is_rejected(periodic_pair):
    """A generated street's start/end closure: ICP converged 3.2 m along the street and every score
    gate passed it. Fine passes only (a proximity guess is already close), guesses 3 and 4 m along
    the street: one converges to the truth and is accepted, the other 4 m off with inlier ratio,
    overlap and Hessian above their gates and is rejected as ambiguous; nothing accepted is more
    than 1 m off."""
    reference, query, T_true = periodic_pair
    fine = {**LOOP_CONFIG, "icp_scales": [1.0, 0.5]}
    unchecked = IcpVerifier(LidarLoopConfig(**fine, ambiguity_check=False))
    checked = IcpVerifier(LidarLoopConfig(**fine))
    aliased, accepted = [], 0
    for along_m in (3.0, 4.0):
        guess = _guess(T_true, along_m)
        raw = unchecked.verify(reference, query, guess, limit_correction=False)
        raw_error_m, _ = relative_motion(T_true, raw.T_ref_query)
        result = checked.verify(reference, query, guess, limit_correction=False)
        if raw.accepted and 1.0 < raw_error_m < PERIOD_M / 2:
            aliased.append(raw_error_m)
            assert not result.accepted, (along_m, raw_error_m, result.scores)
            assert result.reason.startswith("ambiguous"), result.reason
        if result.accepted:
            accepted += 1
            error_m, error_deg = relative_motion(T_true, result.T_ref_query)
            assert error_m < 1.0 and error_deg < 1.0, (along_m, result.scores)
    assert aliased, "no guess converged a few metres along the street: the test checks nothing"
    assert accepted, "no guess converged to the truth: the acceptance is not checked"


def test_true_loop_on_the_periodic_street_is_accepted(periodic_pair):
    reference, query, T_true = periodic_pair
    verifier = IcpVerifier(LidarLoopConfig(**LOOP_CONFIG))
    result = verifier.verify(reference, query, _guess(T_true, 1.0), limit_correction=False)
    assert result.accepted, result.reason
    error_m, error_deg = relative_motion(T_true, result.T_ref_query)
    assert error_m < 0.5 and error_deg < 0.5, result.scores
    # the aliased solutions exist (found one period away) but score clearly worse
    assert result.scores["ambiguity_separation_m"] > PERIOD_M - 2.0
    ratio = LidarLoopConfig().ambiguity_score_ratio
    assert result.scores["ambiguity_alternative_score"] < ratio * result.scores["ambiguity_score"]


def test_graph_gate_rejects_a_correction_outside_the_odometry_uncertainty():
    """A 300 m chain of 30 m odometry edges (configs/kitti.yaml sigmas): the true relative pose
    plus a realistic drift passes the chi-square gate, one period (16 m) along the street not."""
    cfg = PoseGraphConfig(
        odometry_translation_sigma_m=0.05,
        odometry_translation_sigma_per_m=0.01,
        odometry_rotation_sigma_rad=0.002,
        odometry_rotation_sigma_rad_per_m=0.0003,
    )
    graph = PoseGraph(cfg)
    for k in range(11):
        graph.add_anchor(k, _pose(30.0 * k))
    covariance = graph.relative_covariance(0, 10)
    assert covariance.shape == (6, 6)
    assert np.all(np.linalg.eigvalsh(covariance) > 0)
    T_graph = np.linalg.inv(graph.pose(0)) @ graph.pose(10)
    loop_covariance = np.diag([1e-4] * 3 + [0.01] * 3)
    limit = chi2.ppf(LidarLoopConfig().graph_consistency_probability, 6)
    drifted = T_graph @ _pose(0.8, 0.5)
    assert mahalanobis_distance2(T_graph, covariance, drifted, loop_covariance) < limit
    aliased = T_graph @ _pose(PERIOD_M)
    assert mahalanobis_distance2(T_graph, covariance, aliased, loop_covariance) > limit


def test_fine_restart_keeps_the_better_scoring_registration(periodic_pair):
    """From a guess 4 m along the street the wide first passes end at a worse minimum than the
    fine passes alone; the verifier keeps the one with more inliers and says so."""
    reference, query, T_true = periodic_pair
    guess = _guess(T_true, 4.0)
    config = LidarLoopConfig(**LOOP_CONFIG, ambiguity_check=False, icp_point_to_plane=False)
    restarted = IcpVerifier(config).verify(reference, query, guess)
    single = IcpVerifier(config.model_copy(update={"icp_fine_restart": False})).verify(
        reference, query, guess
    )
    assert "icp_fine_restart" not in single.scores
    assert restarted.scores["icp_fine_restart"] == 1.0
    assert restarted.scores["inlier_ratio"] > single.scores["inlier_ratio"] + 0.05
    fine = IcpVerifier(config).align(reference, query, guess, scales=config.icp_scales[-2:])
    np.testing.assert_allclose(restarted.T_ref_query, fine)
    correction_m, _ = relative_motion(guess, fine)
    assert restarted.scores["icp_correction_m"] == pytest.approx(correction_m)


def test_point_to_plane_finish_brings_the_true_loop_closer(periodic_pair):
    """KISS-ICP's point-to-point result of the true loop is 0.18 m off; the point-to-plane
    finish on the reference's normals takes it closer, and the edge's Hessian is taken there."""
    reference, query, T_true = periodic_pair
    guess = _guess(T_true, 0.5)
    config = LidarLoopConfig(**LOOP_CONFIG, ambiguity_check=False)
    finished = IcpVerifier(config).verify(reference, query, guess)
    point_to_point = IcpVerifier(config.model_copy(update={"icp_point_to_plane": False})).verify(
        reference, query, guess
    )
    assert finished.accepted and point_to_point.accepted
    assert finished.scores["icp_point_to_plane"] == 1.0
    error_m, error_deg = relative_motion(T_true, finished.T_ref_query)
    before_m, _ = relative_motion(T_true, point_to_point.T_ref_query)
    assert error_m < 0.5 * before_m and error_deg < 0.2
    assert finished.covariance is not None
    assert not np.allclose(finished.covariance, point_to_point.covariance)


def test_fine_restart_runs_only_after_a_real_coarse_correction(periodic_pair):
    """The restart of the 4 m guess above is skipped when its gate lies beyond the coarse
    correction: then the verifier keeps the coarse-to-fine result, as with no restart at all."""
    reference, query, T_true = periodic_pair
    guess = _guess(T_true, 4.0)
    config = LidarLoopConfig(**LOOP_CONFIG, ambiguity_check=False, icp_point_to_plane=False)
    coarse = IcpVerifier(config).align(reference, query, guess)
    moved_m, moved_deg = relative_motion(guess, coarse)
    assert moved_m >= config.icp_fine_restart_min_correction_m  # the restart test's case
    gated = config.model_copy(
        update={
            "icp_fine_restart_min_correction_m": moved_m + 1.0,
            "icp_fine_restart_min_correction_deg": moved_deg + 1.0,
        }
    )
    result = IcpVerifier(gated).verify(reference, query, guess)
    assert "icp_fine_restart" not in result.scores
    np.testing.assert_allclose(result.T_ref_query, coarse)


def test_thinned_coarse_passes_reach_the_full_density_pose(periodic_pair):
    """The wide passes on the query thinned to 1 m voxels end where the full-density passes do
    (from 2 m along the street and 1 deg of yaw off the true loop): they only have to bring the
    guess into the fine passes' reach."""
    reference, query, T_true = periodic_pair
    guess = _guess(T_true, 2.0)
    yaw = np.deg2rad(1.0)
    guess[:2, :2] = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    guess[:3, :3] = guess[:3, :3] @ T_true[:3, :3]
    config = LidarLoopConfig(**LOOP_CONFIG, ambiguity_check=False)
    thinned = IcpVerifier(config).verify(reference, query, guess)
    full = IcpVerifier(config.model_copy(update={"icp_coarse_voxel_m": 0.0})).verify(
        reference, query, guess
    )
    assert thinned.accepted and full.accepted
    distance_m, distance_deg = relative_motion(full.T_ref_query, thinned.T_ref_query)
    assert distance_m < 0.02 and distance_deg < 0.05
    error_m, _ = relative_motion(T_true, thinned.T_ref_query)
    assert error_m < 0.2


def test_a_quarter_of_the_query_profiles_the_same_alternative(periodic_pair):
    """The score profile counted on a random quarter of the query (as localisation counts its
    coarse subset) seeds the same re-registration one period along the street, and the returned
    scores still count every query point."""
    reference, query, T_true = periodic_pair
    verifier = IcpVerifier(LidarLoopConfig(**LOOP_CONFIG, ambiguity_check=False))

    def align(guess: np.ndarray) -> np.ndarray:
        return verifier.align(reference, query, guess, scales=[1.0, 0.5])

    pick = np.random.default_rng(0).choice(len(query), len(query) // 4, replace=False)
    kwargs = {
        "inlier_distance_m": 0.5,
        "step_m": 1.0,
        "max_offset_m": 20.0,
        "min_separation_m": 2.0,
        "min_separation_deg": 2.0,
        "max_realignments": 2,
    }
    full = find_ambiguity(reference, query, T_true, None, align, **kwargs)
    quarter = find_ambiguity(
        reference, query, T_true, None, align, **kwargs, profile_query=query[pick]
    )
    assert quarter[0] == full[0]
    assert full[1] is not None and quarter[1] is not None
    assert abs(full[1].separation_m - PERIOD_M) < 1.0
    assert quarter[1].separation_m == pytest.approx(full[1].separation_m, abs=0.1)
    assert quarter[1].score == pytest.approx(full[1].score, abs=0.02)
