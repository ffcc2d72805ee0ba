"""The LiDAR map benchmark's parts: the numpy TSDF, the observed surface and its scores."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from benchmarks.bench_lidar_map import build_parser, stretches
from benchmarks.harness import lidar_surface
from benchmarks.harness.lidar_surface import (
    OBSERVED_DISTANCE_M,
    ScanSet,
    observed_mask,
    point_precision,
    region_scores,
    scan_set,
)
from benchmarks.harness.lidar_tsdf import BLOCK, BYTES_PER_VOXEL, LidarTsdf

SENSOR_Z_M = 2.0
WALL_X_M = 10.0


def _scan(
    x_m: float = 0.0, num_rays: int = 60_000, seed: int = 0, max_range_m: float = 30.0
) -> np.ndarray:
    """Rays from a sensor at x = ``x_m``, 2 m above the floor z = 0, in front of the wall
    x = 10: the first hit of each, in the sensor frame (axes as the world's)."""
    directions = np.random.default_rng(seed).normal(size=(num_rays, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    with np.errstate(divide="ignore"):
        to_floor = np.where(directions[:, 2] < 0, -SENSOR_Z_M / directions[:, 2], np.inf)
        to_wall = np.where(directions[:, 0] > 0, (WALL_X_M - x_m) / directions[:, 0], np.inf)
    hit = np.minimum(to_floor, to_wall)
    keep = hit < max_range_m
    return directions[keep] * hit[keep, None]


def _sensor_pose(x_m: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x_m, 0.0, SENSOR_Z_M]
    return T


def _distance_to_scene(points_W: np.ndarray, x_shift_m: float = 0.0) -> np.ndarray:
    """Distance to the floor z = 0 or the wall x = 10 + shift (world frame), the nearer."""
    return np.minimum(np.abs(points_W[:, 2]), np.abs(points_W[:, 0] - WALL_X_M - x_shift_m))


def _scene_mesh() -> trimesh.Trimesh:
    floor = trimesh.creation.box([30.0, 30.0, 0.01])
    floor.apply_translation([0.0, 0.0, -0.005])
    wall = trimesh.creation.box([0.01, 30.0, 10.0])
    wall.apply_translation([WALL_X_M + 0.005, 0.0, 5.0])
    return trimesh.util.concatenate([floor, wall])


def test_tsdf_mesh_lies_on_the_scanned_surfaces() -> None:
    tsdf = LidarTsdf(0.2)
    for x in (0.0, 1.0):
        tsdf.integrate(_scan(x, seed=int(x)), _sensor_pose(x))
    mesh = tsdf.extract_mesh()
    assert len(mesh.faces) > 1000
    error = _distance_to_scene(np.asarray(mesh.vertices))
    assert np.mean(error < 0.1) > 0.9 and np.percentile(error, 99) < 0.2
    # both surfaces are there, and nothing beyond the wall
    vertices = np.asarray(mesh.vertices)
    assert (np.abs(vertices[:, 0] - WALL_X_M) < 0.2).sum() > 100
    assert (np.abs(vertices[:, 2]) < 0.2).sum() > 100
    assert vertices[:, 0].max() < WALL_X_M + 0.5


def test_tsdf_memory_counts_the_allocated_blocks() -> None:
    tsdf = LidarTsdf(0.2)
    assert tsdf.memory_bytes() == 0 and len(tsdf.extract_mesh().faces) == 0
    # one point straight ahead: the voxels within +-0.6 m of it along x, in one or two blocks
    tsdf.integrate(np.array([[5.05, 0.05, 0.05]]), np.eye(4))
    assert tsdf.num_voxels in (6, 7)
    assert tsdf.memory_bytes() in (BLOCK**3 * BYTES_PER_VOXEL, 2 * BLOCK**3 * BYTES_PER_VOXEL)


def test_a_scan_observes_only_the_surface_near_its_points_in_range() -> None:
    points_S = _scan(max_range_m=100.0)
    scans = scan_set([points_S], _sensor_pose()[None], max_range_m=100.0)
    samples = np.array([[3.0, 0.0, 0.0], [WALL_X_M, 0.0, SENSOR_Z_M], [40.0, 20.0, 0.0]])
    dense = ScanSet(
        np.concatenate([scans.points_W, samples + np.array([0.0, 0.0, 0.5 * OBSERVED_DISTANCE_M])]),
        np.concatenate([scans.ranges_m, [3.6, 10.0, 44.8]]),
    )
    assert observed_mask(samples, dense, 100.0).tolist() == [True, True, True]
    assert observed_mask(samples, dense, 30.0).tolist() == [True, True, False]
    lifted = ScanSet(dense.points_W + np.array([0.0, 0.0, 2 * OBSERVED_DISTANCE_M]), dense.ranges_m)
    assert not observed_mask(samples[:1], lifted, 100.0).any()


def test_scores_of_the_truth_and_of_a_shifted_copy(monkeypatch) -> None:
    monkeypatch.setattr(lidar_surface, "MAX_SCORED_SAMPLES", 5000)  # fewer samples: faster
    monkeypatch.setattr(lidar_surface, "REFERENCE_SAMPLES", 50_000)
    gt = _scene_mesh()
    rng = np.random.default_rng(1)
    observed = np.c_[rng.uniform(-10, 8, 5000), rng.uniform(-10, 10, 5000), np.zeros(5000)]
    positions = np.array([[0.0, 0.0, SENSOR_Z_M]])
    perfect = region_scores(gt, gt, observed, positions, 30.0)
    assert perfect["precision_0.1"] > 0.99 and perfect["recall_0.1"] > 0.99
    assert perfect["accuracy_m"] < 0.01 and perfect["completion_m"] < 0.01
    lifted = gt.copy()  # floor and wall 15 cm off
    lifted.apply_translation([0.15, 0.0, 0.15])
    off = region_scores(lifted, gt, observed, positions, 30.0)
    assert off["recall_0.1"] < 0.05 and off["recall_0.2"] > 0.95
    assert off["completion_m"] == pytest.approx(0.14, abs=0.005)  # to the lifted underside
    # against points alone (here 11 cm apart): the truth is precise, the lifted copy is not
    points = trimesh.sample.sample_surface(gt, 100_000, seed=4)[0]
    truth = point_precision(gt, points, positions, 30.0)
    shifted = point_precision(lifted, points, positions, 30.0)
    assert truth["precision_0.2"] > 0.99 and truth["precision_0.1"] > 0.8
    assert shifted["precision_0.1"] < 0.1 and shifted["precision_0.5"] > 0.99


def test_stretches_cover_the_scans_without_a_short_tail() -> None:
    assert stretches(150, 75) == [(0, 75), (75, 150)]
    assert stretches(4541, 600)[-1] == (4200, 4541)
    assert stretches(620, 600) == [(0, 620)]
    assert stretches(100, 600) == [(0, 100)]


def test_quick_and_full_are_exclusive() -> None:
    assert build_parser().parse_args(["--full"]).quick is False
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--quick", "--full"])
