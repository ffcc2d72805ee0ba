"""The LiDAR map benchmark's parts: the numpy TSDF, the observed surface and its scores, the
picture of a street corner from maps in other frames."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from benchmarks.bench_lidar_map import build_parser, stretches
from benchmarks.harness import lidar_surface
from benchmarks.harness.kitti import STANDARD_STREET, STREETS
from benchmarks.harness.lidar_surface import (
    OBSERVED_DISTANCE_M,
    ScanSet,
    observed_mask,
    point_precision,
    region_scores,
    scan_set,
)
from benchmarks.harness.lidar_tsdf import BLOCK, BYTES_PER_VOXEL, LidarTsdf
from benchmarks.harness.paths import DATA
from benchmarks.lidar_map_picture import corner_panels, corner_picture
from tests.helpers import positions_along

MULRAN_SCANS = DATA / "mulran_riverside02_keyframes" / "scans"
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


def test_street_picks_one_of_the_variant_benchmarks_streets() -> None:
    assert build_parser().parse_args([]).street == STANDARD_STREET
    assert STREETS[STANDARD_STREET] == {}  # the standard street: the generator's defaults
    assert STREETS[build_parser().parse_args(["--street", "sparse"]).street] == {
        "street_style": "sparse"
    }
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--street", "no such street"])


def _poses_along(*points: tuple[float, float]) -> np.ndarray:
    """Sensor poses every metre along the polyline through ``points``, 2 m up."""
    positions = positions_along(points, 1.0, SENSOR_Z_M)
    poses = np.tile(np.eye(4), (len(positions), 1, 1))
    poses[:, :3, 3] = positions
    return poses


def test_corner_picture_aligns_the_slam_map_onto_the_ground_truth(tmp_path) -> None:
    # an L-shaped drive along a floor with a block at its corner; the SLAM run's map and poses
    # are the same in a frame turned by 30 deg and moved by about 40 m
    gt_poses = _poses_along((-40.0, 0.0), (0.0, 0.0), (0.0, 40.0))
    block = trimesh.creation.box([6.0, 6.0, 4.0])
    block.apply_translation([6.0, -6.0, 2.0])
    world = trimesh.util.concatenate([_scene_mesh(), block])
    T_S_W = trimesh.transformations.rotation_matrix(np.radians(30), [0, 0, 1])
    T_S_W[:3, 3] = [40.0, -10.0, 1.0]
    slam_map = world.copy().apply_transform(T_S_W)
    run = {"vertices": world.vertices, "faces": world.faces, "poses": gt_poses}
    slam = {"vertices": slam_map.vertices, "faces": slam_map.faces, "poses": T_S_W @ gt_poses}
    runs = {"gt": {"neural map": run}, "kiss-icp": {"neural map": slam}}
    scorer = SimpleNamespace(gt_poses=gt_poses, gt_region=world)

    corner, (gt_row, slam_row) = corner_panels(runs, scorer, {"neural map": 80.0})
    np.testing.assert_allclose(corner.centre_W[:2], [0.0, 0.0], atol=1.0)
    assert [p.title for p in gt_row] == [
        "ground-truth poses, map to 80 m (as configured)",
        "ground-truth mesh",
    ]
    (from_gt, truth), (from_slam,) = gt_row, slam_row
    np.testing.assert_allclose(from_slam.trajectory_W, gt_poses[:, :3, 3], atol=1e-6)
    both = np.isfinite(from_gt.heights) & np.isfinite(from_slam.heights)
    assert both.sum() > 0.99 * np.isfinite(from_gt.heights).sum() > 0
    same = np.abs(from_slam.heights[both] - from_gt.heights[both]) < 0.05
    assert same.mean() > 0.98  # pixels on an edge may take the wall's or the floor's height
    raised_gt, raised_slam = from_gt.heights > 0, from_slam.heights > 0  # the block and the wall
    assert (raised_gt & raised_slam).sum() > 0.9 * (raised_gt | raised_slam).sum() > 0
    assert np.mean(np.isfinite(truth.heights) == np.isfinite(from_gt.heights)) > 0.995
    top = from_gt.heights[np.isfinite(from_gt.heights)].max()
    assert top == pytest.approx(10.0 - SENSOR_Z_M, abs=0.01)  # the wall's top, not the floor

    caption = corner_picture(tmp_path / "corner.png", runs, scorer, {"neural map": 80.0})
    assert (tmp_path / "corner.png").stat().st_size < 400_000
    assert "columns: map to 80 m (as configured), the ground-truth mesh" in caption


@pytest.mark.skipif(
    not MULRAN_SCANS.is_dir(), reason=f"no MulRan keyframes under {MULRAN_SCANS.parent}"
)
def test_mulran_map_is_scored_in_the_frame_its_run_claims() -> None:
    """A run's mesh is in its first scan's frame; the reference poses' first pose is not the
    identity (about 1 deg off). A mesh lying on the first keyframe's points in that scan's frame
    must score as precise, which only holds once carried by the first reference pose."""
    from benchmarks.bench_lidar_map import _mulran_config, mulran_scores

    _, source = _mulran_config(1, [])
    points = source[0].points
    offsets = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])
    result = {
        "vertices": (points[:, None, :] + offsets).reshape(-1, 3),
        "faces": np.arange(3 * len(points)).reshape(-1, 3),
    }
    run_poses = np.eye(4)[None]
    (scored,) = mulran_scores(result, run_poses, 1, [80.0])
    assert scored["precision_0.1"] > 0.95
    assert scored["accuracy_m"] < 0.03
    unmoved = mulran_scores(result, None, 1, [80.0])[0]
    assert unmoved["precision_0.1"] < 0.8
