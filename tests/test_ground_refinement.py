"""Ground refinement of LiDAR odometry: the ground map, and vertical drift removed on a hill."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from frontends.frame import Frame
from frontends.odometry.base import Odometry, OdometryResult
from slam.algorithm.ground_refinement import (
    GroundHeightMap,
    GroundRefinedOdometry,
    GroundRefinementConfig,
)
from slam.evaluation.metrics.trajectory import ate_per_axis_rmse


def _terrain(xy: np.ndarray) -> np.ndarray:
    """A road climbing 6 m over a crest, hills across it."""
    x, y = xy[:, 0], xy[:, 1]
    return 6.0 / (1.0 + np.exp(-(x - 60.0) / 12.0)) + 0.8 * np.sin(y / 9.0) * np.cos(x / 23.0)


def _trajectory(n: int, step_m: float = 1.5, sensor_height_m: float = 1.73) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    x = np.arange(n) * step_m
    z = _terrain(np.column_stack([x, np.zeros(n)]))
    slope = np.gradient(z, x)
    poses[:, :3, :3] = Rotation.from_euler(
        "ZYX", np.column_stack([0.02 * np.sin(x / 30.0), -np.arctan(slope), np.zeros(n)])
    ).as_matrix()
    poses[:, :3, 3] = np.column_stack([x, np.zeros(n), z + sensor_height_m])
    return poses


def _scan(T_W_S: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Ground points within 40 m plus a few walls, in the sensor frame, with 2 cm noise."""
    r = np.sqrt(rng.uniform(9.0, 1600.0, 6000))
    a = rng.uniform(0.0, 2 * np.pi, 6000)
    xy = T_W_S[:2, 3] + np.column_stack([r * np.cos(a), r * np.sin(a)])
    ground = np.column_stack([xy, _terrain(xy)])
    wall_x = T_W_S[0, 3] + rng.uniform(-30.0, 30.0, 800)
    walls = np.column_stack(
        [wall_x, rng.choice([-12.0, 12.0], 800), _terrain(np.column_stack([wall_x, 0 * wall_x]))]
    )
    walls[:, 2] += rng.uniform(0.0, 8.0, 800)
    points_W = np.vstack([ground, walls]) + rng.normal(0.0, 0.02, (6800, 3))
    T_S_W = np.linalg.inv(T_W_S)
    return points_W @ T_S_W[:3, :3].T + T_S_W[:3, 3]


class PitchDriftingOdometry(Odometry):
    """Ground-truth motion with a pitch bias per scan: the vertical drift of a front-end."""

    def __init__(self, gt: np.ndarray, pitch_rad_per_scan: float) -> None:
        self._gt = gt
        self._bias = np.eye(4)
        self._bias[:3, :3] = Rotation.from_euler("y", pitch_rad_per_scan).as_matrix()
        self._i = -1
        self._pose = gt[0].copy()

    def register(self, frame: Frame) -> OdometryResult:
        self._i += 1
        if self._i > 0:
            step = np.linalg.inv(self._gt[self._i - 1]) @ self._gt[self._i]
            self._pose = self._pose @ step @ self._bias
        return OdometryResult(self._pose.copy())


def test_ground_map_averages_flat_cells_and_skips_walls() -> None:
    ground = GroundHeightMap(cell_m=1.0)
    floor = np.array([[0.2, 0.2, 1.0], [0.7, 0.6, 1.1], [2.5, 0.5, -0.5], [2.6, 0.4, -0.45]])
    wall = np.array([[5.5, 0.5, 0.0], [5.5, 0.5, 2.0]])
    ground.add_flat_cells(np.vstack([floor, wall]), flatness_m=0.15)
    ground.add_flat_cells(floor + np.array([0.0, 0.0, 0.2]), flatness_m=0.15)
    h = ground.height(np.array([[0.5, 0.5], [2.5, 0.5], [5.5, 0.5], [9.0, 9.0]]), 2)
    np.testing.assert_allclose(h[:2], [1.15, -0.375])
    assert np.isnan(h[2]) and np.isnan(h[3])  # a wall is not ground; an unseen cell is unknown
    assert np.isnan(ground.height(np.array([[0.5, 0.5]]), 3)[0])  # seen only twice


def test_ground_map_forgets_cells_not_seen_within_its_memory() -> None:
    """A cell mapped on a first visit is gone after ``memory_m`` of travel without an update, so
    a revisit maps it afresh instead of averaging in (and snapping to) the old height."""
    ground = GroundHeightMap(cell_m=1.0, memory_m=50.0)
    first = np.array([[0.2, 0.2, 1.0], [0.7, 0.6, 1.1]])
    road = np.array([[30.2, 0.2, 0.0], [30.7, 0.6, 0.1]])
    ground.add_flat_cells(first, 0.15, travelled_m=0.0)
    ground.add_flat_cells(road, 0.15, travelled_m=40.0)
    assert ground.height(np.array([[0.5, 0.5]]), 1)[0] == pytest.approx(1.05)  # 40 m ago: kept
    ground.add_flat_cells(road, 0.15, travelled_m=60.0)
    h = ground.height(np.array([[0.5, 0.5], [30.5, 0.5]]), 1)
    assert np.isnan(h[0]) and h[1] == pytest.approx(0.05)  # 60 m without an update: gone
    ground.add_flat_cells(first + np.array([0.0, 0.0, 0.5]), 0.15, travelled_m=200.0)
    h = ground.height(np.array([[0.5, 0.5], [30.5, 0.5]]), 1)
    assert h[0] == pytest.approx(1.55) and np.isnan(h[1])  # the revisit's height alone


def test_ground_refinement_removes_the_vertical_drift_on_a_hill() -> None:
    gt = _trajectory(90)
    rng = np.random.default_rng(0)
    scans = [_scan(T, rng) for T in gt]
    cfg = GroundRefinementConfig(enabled=True)
    alone = PitchDriftingOdometry(gt, 0.001)
    drifting = np.array([alone.register(Frame(i, 0.1 * i, s)).T_W_S for i, s in enumerate(scans)])
    inner = PitchDriftingOdometry(gt, 0.001)
    refined_odometry = GroundRefinedOdometry(inner, cfg)
    refined = np.array(
        [refined_odometry.register(Frame(i, 0.1 * i, s)).T_W_S for i, s in enumerate(scans)]
    )
    before = ate_per_axis_rmse(drifting, gt)
    after = ate_per_axis_rmse(refined, gt)
    assert before[2] > 0.3  # 0.057 deg a scan: metres of height after 135 m
    assert after[2] < 0.2 * before[2], (before, after)
    assert np.hypot(*after[:2]) <= np.hypot(*before[:2]) + 0.01, (before, after)
    assert refined_odometry.last_matched > cfg.min_points
