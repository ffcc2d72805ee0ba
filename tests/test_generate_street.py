"""The generated street along the real KITTI 00 trajectory: its scene (blocks, along-track
structure, a clear path, the real elevation) and what KISS-ICP makes of its scans."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from frontends.errors import DatasetError
from frontends.generate import LidarConfig, generate_lidar_sequence
from frontends.generate.raycast import Raycaster
from frontends.generate.street import street_scene
from frontends.generate.trajectories import kitti_lidar_trajectory
from frontends.sources import make_source
from tests.dataset_files import DATA
from tests.helpers import MeshDistance, mesh_distance

KITTI_POSES = DATA / "kitti" / "poses" / "00.txt"
KITTI_CALIB = DATA / "kitti" / "sequences" / "00" / "calib.txt"
RANGE_SIGMA_M = LidarConfig().range_noise_m


@pytest.mark.skipif(
    not KITTI_POSES.is_file(), reason=f"real KITTI poses not found at {KITTI_POSES}"
)
def test_street_along_a_real_kitti_trajectory(tmp_path):
    source = make_source(
        "generated",
        kind="lidar",
        root=tmp_path,
        num_frames=6,
        trajectory="kitti",
        kitti_poses=KITTI_POSES,
        kitti_calib=KITTI_CALIB,
        start=1000,
        step=10,
        azimuth_steps=256,
    )
    real = kitti_lidar_trajectory(KITTI_POSES, KITTI_CALIB, start=1000, num_frames=6, step=10)
    np.testing.assert_allclose(source.gt_poses, np.linalg.inv(real[0]) @ real, atol=1e-6)
    mesh = trimesh.load(source.gt_mesh_path)
    assert mesh_distance(mesh, source.gt_poses[:, :3, 3]).min() > 1.5
    frame = source[5]
    world = frame.points @ frame.T_W_S_gt[:3, :3].T + frame.T_W_S_gt[:3, 3]
    assert mesh_distance(mesh, world[::7]).mean() < 1.5 * RANGE_SIGMA_M
    with pytest.raises(DatasetError, match="needs frame"):
        kitti_lidar_trajectory(KITTI_POSES, KITTI_CALIB, start=4500, num_frames=100)


def _kiss_icp_path_lengths(root: Path, num_scans: int) -> tuple[float, float]:
    """Path length over the first ``num_scans`` scans: KISS-ICP's estimate and ground truth."""
    from frontends.odometry import make_odometry

    source = make_source("kitti", root=root, sequence="00")
    # Generated scans are taken at one instant: nothing to deskew.
    odometry = make_odometry("kiss-icp", data={"deskew": False})
    est = np.stack([odometry.register(source[i]).T_W_S for i in range(num_scans + 1)])
    gt = source.gt_poses[: num_scans + 1]

    def length(poses: np.ndarray) -> float:
        return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())

    return length(est), length(gt)


@pytest.mark.skipif(
    not KITTI_POSES.is_file(), reason=f"real KITTI poses not found at {KITTI_POSES}"
)
@pytest.mark.parametrize("start", [0, 3000])
def test_kiss_icp_tracks_the_street_from_the_first_scan(tmp_path, start):
    """The street has along-track structure everywhere: ICP is not degenerate along the road,
    so KISS-ICP (starting from a zero-velocity guess) follows the car from its first scans."""
    generate_lidar_sequence(
        tmp_path,
        num_frames=16,
        trajectory="kitti",
        kitti_poses=KITTI_POSES,
        kitti_calib=KITTI_CALIB,
        start=start,
        azimuth_steps=512,
        seed=2,
        workers=1,
    )
    est_m, gt_m = _kiss_icp_path_lengths(tmp_path, 15)
    assert gt_m > 10.0  # the car drives ~0.7-0.9 m per scan here
    assert abs(est_m - gt_m) < 0.15 * gt_m, (est_m, gt_m)


def test_street_has_along_track_structure_and_keeps_the_path_clear():
    """Along a straight road, facades break into blocks with gaps, and surfaces facing along
    the road (block ends, cars, poles, pilasters) stand all along it; nothing is on the path."""
    x = np.arange(0.0, 200.0, 1.0)
    path = np.column_stack([x, np.zeros_like(x), np.full_like(x, 1.73)])
    scene = street_scene(path, seed=3)
    again = street_scene(path, seed=3)
    np.testing.assert_array_equal(scene.mesh.vertices, again.mesh.vertices)
    assert not np.array_equal(street_scene(path, seed=4).mesh.vertices, scene.mesh.vertices)
    mesh = scene.mesh
    # The street continues behind the first pose and beyond the last one.
    centers = mesh.triangles_center
    tall = (centers[:, 2] > 3.0) & (np.abs(centers[:, 1]) < 20.0)
    assert centers[tall, 0].min() < -20.0 and centers[tall, 0].max() > 220.0
    # Faces whose normal points along the road, above the ground, near the road: in every
    # 10 m stretch on each side.
    along = (np.abs(mesh.face_normals[:, 0]) > 0.9) & (centers[:, 2] > 0.3)
    for side in (1.0, -1.0):
        near = along & (side * centers[:, 1] > 2.0) & (side * centers[:, 1] < 20.0)
        stretch = np.floor(centers[near, 0] / 10.0).astype(int)
        assert set(range(0, 20)) <= set(stretch.tolist()), side
    # Facades are broken into blocks: a ray along the facade line, 1 m in front of the
    # building row, is not blocked over the full length, and rays across the road at storey
    # height find gaps between blocks.
    raycaster = Raycaster(mesh)
    xs = np.arange(0.0, 200.0, 0.5)
    for side in (1.0, -1.0):
        origins = np.column_stack([xs, np.zeros_like(xs), np.full_like(xs, 6.0)])
        directions = np.tile([0.0, side, 0.0], (len(xs), 1))
        distance, _ = raycaster.first_hit(origins, directions)
        open_fraction = np.mean(distance > 20.0)
        assert 0.03 < open_fraction < 0.6, (side, open_fraction)
    clearance = MeshDistance(mesh, spacing_m=0.5)(path)
    assert clearance.min() > 1.5, clearance.min()


@pytest.mark.skipif(not KITTI_POSES.is_file(), reason="needs ../shared/data/kitti (KITTI 00 poses)")
def test_street_ground_follows_the_real_kitti_elevation():
    """Under the car the ground is the real KITTI 00 height minus the sensor height (its slopes
    and crests), with or without hills beside the road; the hills rise only away from it."""
    poses = kitti_lidar_trajectory(KITTI_POSES, KITTI_CALIB, start=2000, num_frames=250, step=3)
    path = poses[:, :3, 3]
    assert np.ptp(path[:, 2]) > 3.0  # this stretch of KITTI 00 climbs
    relief_m = 4.0
    tangent = np.gradient(path[:, :2], axis=0)
    left = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    down = np.tile([0.0, 0.0, -1.0], (len(path), 1))
    ground = {}
    for relief in (0.0, relief_m):
        raycaster = Raycaster(street_scene(path, seed=0, relief_m=relief).mesh)
        distance, _ = raycaster.first_hit(path, down)
        np.testing.assert_allclose(distance, 1.73, atol=0.05)
        beside = np.column_stack([path[:, :2] + 35.0 * left, path[:, 2] + 100.0])
        distance, _ = raycaster.first_hit(beside, down)
        ground[relief] = beside[:, 2] - distance
    # 35 m beside the road: level with the road without relief (up to a few rays on a bush or a
    # wall), hills and hollows of up to relief_m with it.
    _, nearest = cKDTree(path[:, :2]).query(path[:, :2] + 35.0 * left)
    level = ground[0.0] - (path[nearest, 2] - 1.73)
    not_roof = np.abs(level) < 2.0  # buildings are at least 6.5 m high
    assert not_roof.mean() > 0.3
    assert np.percentile(np.abs(level[not_roof]), 80) < 0.05
    hills = ground[relief_m] - ground[0.0]
    on_ground = not_roof & (np.abs(hills) < relief_m + 0.05)
    assert on_ground.mean() > 0.3
    assert np.ptp(hills[on_ground]) > 0.8 * relief_m
