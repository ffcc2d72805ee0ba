"""Odometry front-ends: KISS-ICP on real KITTI scans, OpenCV RGB-D odometry on rendered views with
a known motion and on real 7-Scenes frames, and ground-truth odometry."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from frontends.errors import DatasetError
from frontends.frame import Frame, Intrinsics
from frontends.odometry import make_odometry
from frontends.odometry.ground_truth import GroundTruthOdometry
from frontends.odometry.kiss import KissIcpOdometry
from frontends.odometry.rgbd import RgbdOdometry
from slam.evaluation.metrics import ate_rmse

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
KITTI_SCANS = DATA / "kitti" / "real_scans"
SEVEN_SCENES = DATA / "7scenes_redkitchen"


def _se3(rotvec=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _angle_deg(T: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()))


# --- a tiny renderer: a textured room seen by a pinhole camera --------------------------------

INTRINSICS = Intrinsics(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)


def _room() -> trimesh.Trimesh:
    walls = trimesh.creation.box(extents=(6.0, 5.0, 3.0))
    walls.invert()  # normals inwards
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cube.apply_translation((1.0, 0.5, -1.0))
    ball = trimesh.creation.icosphere(radius=0.5)
    ball.apply_translation((-1.0, -0.5, 0.0))
    return trimesh.util.concatenate([walls, cube, ball])


def _albedo(p: np.ndarray) -> np.ndarray:
    """Smooth but feature-rich grey texture as a function of the world point."""
    return (
        0.5
        + 0.25 * np.sin(7 * p[:, 0] + 3 * p[:, 1]) * np.cos(5 * p[:, 2] + 2 * p[:, 0])
        + 0.2 * np.sin(13 * p[:, 1] - 11 * p[:, 2])
    )


def _render(mesh: trimesh.Trimesh, T_W_C: np.ndarray, index: int) -> Frame:
    intr = INTRINSICS
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    rays_C = np.stack(
        [(u.ravel() - intr.cx) / intr.fx, (v.ravel() - intr.cy) / intr.fy, np.ones(u.size)], 1
    )
    dirs_W = (rays_C / np.linalg.norm(rays_C, axis=1, keepdims=True)) @ T_W_C[:3, :3].T
    origins = np.broadcast_to(T_W_C[:3, 3], dirs_W.shape)
    hits, ray_index, _ = mesh.ray.intersects_location(origins, dirs_W, multiple_hits=False)
    depth = np.zeros(u.size)
    grey = np.zeros(u.size)
    depth[ray_index] = ((hits - T_W_C[:3, 3]) @ T_W_C[:3, :3])[:, 2]
    grey[ray_index] = _albedo(hits)
    grey8 = np.clip(grey * 255, 0, 255).astype(np.uint8).reshape(intr.height, intr.width)
    return Frame(
        index=index,
        timestamp=index / 30.0,
        points=np.zeros((0, 3)),
        depth=depth.reshape(intr.height, intr.width).astype(np.float32),
        rgb=np.repeat(grey8[..., None], 3, axis=2),
        intrinsics=intr,
        T_W_S_gt=T_W_C,
    )


@pytest.fixture(scope="module")
def room() -> trimesh.Trimesh:
    return _room()


# Camera 1.5 m from the room centre looking along +y (OpenCV axes: x right, y down, z forward).
T_W_C0 = _se3((-np.pi / 2, 0.0, 0.0), (0.0, -1.5, 0.0))


# --- RGB-D odometry ---------------------------------------------------------------------------


def test_rgbd_recovers_a_known_motion_in_the_right_direction(room: trimesh.Trimesh) -> None:
    T_C0_C1 = _se3((0.0, 0.03, 0.01), (0.05, -0.02, 0.04))
    odometry = RgbdOdometry(downscale=1)
    assert np.array_equal(odometry.register(_render(room, T_W_C0, 0)).T_W_S, np.eye(4))
    T_W_C1 = odometry.register(_render(room, T_W_C0 @ T_C0_C1, 1)).T_W_S
    # The estimate is T_C0_C1 itself, not its inverse (which is what cv2.Odometry returns).
    np.testing.assert_allclose(T_W_C1[:3, 3], T_C0_C1[:3, 3], atol=3e-3)
    assert _angle_deg(np.linalg.inv(T_C0_C1) @ T_W_C1) < 0.2
    assert np.linalg.norm(T_W_C1[:3, 3] + T_C0_C1[:3, 3]) > 0.1
    assert odometry.num_failures == 0


@pytest.mark.parametrize("downscale", [1, 2])
def test_rgbd_tracks_a_rendered_trajectory(room: trimesh.Trimesh, downscale: int) -> None:
    step = _se3((0.0, 0.02, 0.005), (0.02, 0.0, 0.01))
    gt = np.stack([T_W_C0 @ np.linalg.matrix_power(step, i) for i in range(8)])
    odometry = make_odometry("rgbd", downscale=downscale)
    est = np.stack([odometry.register(_render(room, T, i)).T_W_S for i, T in enumerate(gt)])
    gt_rel = np.linalg.inv(gt[0]) @ gt
    # 16 cm and 8 degrees travelled on noise-free renders; measured 0.2 mm / 0.01 degree.
    assert np.linalg.norm(est[-1, :3, 3] - gt_rel[-1, :3, 3]) < 0.003
    assert _angle_deg(np.linalg.inv(gt_rel[-1]) @ est[-1]) < 0.1
    assert odometry.num_failures == 0


def test_rgbd_failure_falls_back_to_constant_velocity(room: trimesh.Trimesh) -> None:
    step = _se3(t=(0.02, 0.0, 0.01))
    poses = [T_W_C0 @ np.linalg.matrix_power(step, i) for i in range(3)]
    poses.append(poses[-1] @ _se3(t=(0.3, 0.0, 0.15)))  # beyond max_translation_m = 0.15
    odometry = RgbdOdometry(downscale=1, keyframe_translation_m=0.0)
    est = [odometry.register(_render(room, T, i)).T_W_S for i, T in enumerate(poses)]
    assert odometry.num_failures == 1
    expected = est[2] @ np.linalg.inv(est[1]) @ est[2]
    np.testing.assert_allclose(est[3], expected, atol=1e-9)


def test_rgbd_rejects_frames_without_images(room: trimesh.Trimesh) -> None:
    frame = _render(room, T_W_C0, 7)
    odometry = RgbdOdometry()
    with pytest.raises(DatasetError, match=r"frame 7: .*colour image"):
        odometry.register(Frame(7, 0.0, frame.points, depth=frame.depth, intrinsics=INTRINSICS))
    with pytest.raises(DatasetError, match=r"frame 7: .*depth image"):
        odometry.register(Frame(7, 0.0, frame.points, rgb=frame.rgb))
    odometry.register(frame)
    small = Frame(8, 0.0, frame.points, depth=frame.depth[:100], rgb=frame.rgb[:100])
    small.intrinsics = INTRINSICS
    with pytest.raises(DatasetError, match="frame 8: depth is"):
        odometry.register(small)


def test_depth_downscaling_keeps_surfaces_and_drops_edges() -> None:
    from frontends.odometry.rgbd import _downscale_depth

    depth = np.full((4, 6), 2.0, dtype=np.float32)
    depth[0, 0] = 0.0  # one invalid pixel of four: the block stays valid
    depth[2:, 0:2] = [[1.0, 3.0], [1.0, 3.0]]  # a depth edge inside a block
    depth[0:2, 4:6] = [[0.0, 0.0], [0.0, 2.0]]  # mostly invalid
    out = _downscale_depth(depth, 2, max_spread_m=0.07)
    expected = np.array([[2.0, 2.0, 0.0], [0.0, 2.0, 2.0]], dtype=np.float32)
    np.testing.assert_array_equal(out, expected)


def test_rgbd_options_are_validated() -> None:
    with pytest.raises(ValueError, match="max_depth_m"):
        RgbdOdometry(min_depth_m=5.0, max_depth_m=4.0)
    with pytest.raises(ValueError):
        RgbdOdometry(unknown_option=1)


def test_rgbd_on_real_7scenes_frames() -> None:
    if not SEVEN_SCENES.is_dir():
        pytest.skip(f"7-Scenes sample not found at {SEVEN_SCENES}")
    from frontends.sources import make_source

    source = make_source("7scenes", root=SEVEN_SCENES, sequence="seq-01", frames=slice(0, 30))
    odometry = make_odometry("rgbd")
    est = np.stack([odometry.register(frame).T_W_S for frame in source])
    gt = np.linalg.inv(source.gt_poses[0]) @ source.gt_poses
    # Measured: ATE 1.8 mm, end-point error 8.6 mm over these 30 frames (6.7 cm of hand-held
    # motion; the camera moves slowly at the start of the sequence).
    assert ate_rmse(est, gt) < 0.01
    assert np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]) < 0.02
    assert odometry.num_failures == 0


# --- KISS-ICP ---------------------------------------------------------------------------------


def _kitti_scan(number: int) -> np.ndarray:
    scan = np.fromfile(KITTI_SCANS / f"{number:06d}.bin", dtype=np.float32).reshape(-1, 4)
    return scan[:, :3].astype(np.float64)


def test_kiss_icp_on_five_consecutive_real_scans() -> None:
    if not (KITTI_SCANS / "000014.bin").is_file():
        pytest.skip(f"real KITTI scans not found under {KITTI_SCANS}")
    odometry = make_odometry("kiss-icp")
    poses = [odometry.register(Frame(i, 0.1 * i, _kitti_scan(10 + i))).T_W_S for i in range(5)]
    assert np.array_equal(poses[0], np.eye(4))
    for previous, current in itertools.pairwise(poses):
        step = np.linalg.inv(previous) @ current
        # A car driving forward (LiDAR x axis) at ~0.4 m per scan while turning gently.
        assert 0.2 < step[0, 3] < 0.6
        assert abs(step[1, 3]) < 0.15 and abs(step[2, 3]) < 0.05
        assert _angle_deg(step) < 3.0
    assert odometry.voxel_size_m == pytest.approx(1.0)  # max_range / 100, as KISS-ICP does


def test_kiss_icp_recovers_a_known_motion_of_a_synthetic_scene() -> None:
    rng = np.random.default_rng(0)
    # Points on the walls of a 40 x 30 x 10 m box around the sensor, with ground structure.
    box = trimesh.creation.box(extents=(40.0, 30.0, 10.0))
    pillars = [trimesh.creation.cylinder(radius=0.5, height=10.0) for _ in range(6)]
    for pillar in pillars:
        pillar.apply_translation((*rng.uniform(-15, 15, 2), 0.0))
    scene = trimesh.util.concatenate([box, *pillars])
    points_W, _ = trimesh.sample.sample_surface(scene, 60_000, seed=1)
    step = _se3((0.0, 0.0, 0.02), (0.5, 0.1, 0.0))
    odometry = KissIcpOdometry(data={"max_range": 60.0, "min_range": 3.0, "deskew": False})
    odometry_timed = KissIcpOdometry(data={"max_range": 60.0, "min_range": 3.0})
    T_W_S = np.eye(4)
    for i in range(6):
        points_S = (points_W - T_W_S[:3, 3]) @ T_W_S[:3, :3]
        frame = Frame(i, 0.1 * i, points_S)
        result = odometry.register(frame)
        est = result.T_W_S
        np.testing.assert_allclose(est[:3, 3], T_W_S[:3, 3], atol=0.02)
        assert _angle_deg(np.linalg.inv(T_W_S) @ est) < 0.2
        T_W_S = T_W_S @ step
        # nothing to deskew (no point times): the map gets the frame's own points
        assert result.points is None and result.map_points(frame) is frame.points
    # with point times the map gets the scan KISS-ICP deskewed, within its range limits
    timed = Frame(6, 0.6, points_S, point_times=np.linspace(0.0, 1.0, len(points_S)))
    map_points = odometry_timed.register(timed).map_points(timed)
    ranges = np.linalg.norm(points_S, axis=1)
    assert len(map_points) == np.count_nonzero((ranges > 3.0) & (ranges < 60.0))
    assert np.linalg.norm(map_points, axis=1).min() > 3.0


def test_kiss_icp_empty_scan_names_the_frame() -> None:
    odometry = KissIcpOdometry()
    with pytest.raises(DatasetError, match="frame 3: empty scan"):
        odometry.register(Frame(3, 0.0, np.zeros((0, 3))))
    with pytest.raises(DatasetError, match="frame 4: empty scan"):
        odometry.register(Frame(4, 0.0, np.full((10, 3), 500.0)))  # all beyond data.max_range
    with pytest.raises(DatasetError, match="point times"):
        odometry.register(Frame(5, 0.0, np.ones((10, 3)), point_times=np.zeros(3)))


def test_kiss_icp_options() -> None:
    odometry = make_odometry("kiss-icp", data={"max_range": 50.0, "min_range": 2.0})
    assert odometry.voxel_size_m == pytest.approx(0.5)
    assert KissIcpOdometry(mapping={"voxel_size": 0.3}).voxel_size_m == pytest.approx(0.3)
    with pytest.raises(ValueError, match="must exceed"):
        KissIcpOdometry(data={"max_range": 1.0, "min_range": 2.0})
    with pytest.raises(ValueError, match="voxel_size"):
        KissIcpOdometry(mapping={"voxel_size": -1.0})
    with pytest.raises(ValueError, match="Extra inputs"):
        KissIcpOdometry(voxel_size=1.0)  # not a section name
    with pytest.raises(ValueError, match="max_rnge"):
        KissIcpOdometry(data={"max_rnge": 1.0})  # a typo inside a kiss_icp section


def test_kiss_icp_config_is_kiss_icps_own() -> None:
    from kiss_icp.config import KISSConfig

    from frontends.odometry.kiss import KissIcpConfig

    ours = KissIcpConfig.model_validate({"data": {"max_range": 80.0}}).to_kiss()
    assert isinstance(ours, KISSConfig)
    assert ours.mapping.voxel_size == pytest.approx(0.8)  # resolved as kiss_icp's load_config
    defaults = KISSConfig().model_dump()
    got = KissIcpConfig().to_kiss().model_dump()
    for section in ("data", "registration", "adaptive_threshold"):
        assert got[section] == defaults[section]


# --- ground truth -----------------------------------------------------------------------------


def test_ground_truth_odometry_is_relative_to_the_first_frame() -> None:
    gt = [_se3((0.1, 0.2, 0.3), (1.0, 2.0, 3.0)), _se3((0.1, 0.25, 0.3), (1.5, 2.0, 3.0))]
    odometry = make_odometry("gt")
    assert isinstance(odometry, GroundTruthOdometry)
    est = [
        odometry.register(Frame(i, 0.0, np.zeros((0, 3)), T_W_S_gt=T)).T_W_S
        for i, T in enumerate(gt)
    ]
    np.testing.assert_allclose(est[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(est[1], np.linalg.inv(gt[0]) @ gt[1], atol=1e-12)
    frame = Frame(1, 0.0, np.ones((4, 3)), T_W_S_gt=gt[1])
    result = odometry.register(frame)
    assert result.points is None  # the map gets the frame's own points
    assert result.map_points(frame) is frame.points
    with pytest.raises(DatasetError, match="frame 2: the source has no ground-truth pose"):
        odometry.register(Frame(2, 0.0, np.zeros((0, 3))))


# --- generated sequences (read through the real KITTI / TUM loaders) --------------------------


@pytest.fixture(scope="module")
def generated_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("generated")


def test_kiss_icp_on_a_generated_lidar_loop(generated_root: Path) -> None:
    from frontends.sources import make_source

    # One lap of 186 m at ~1 m per scan with sparse (512-firing) scans; the first 60 scans
    # include the first corner.
    source = make_source(
        "generated",
        kind="lidar",
        root=generated_root,
        num_frames=186,
        azimuth_steps=512,
        frames=slice(0, 60),
    )
    odometry = make_odometry("kiss-icp")
    est = np.stack([odometry.register(frame).T_W_S for frame in source])
    gt = np.linalg.inv(source.gt_poses[0]) @ source.gt_poses
    # Measured: ATE 7 cm, end-point error 12 cm and 0.23 degree after 58.5 m.
    assert ate_rmse(est, gt) < 0.3
    assert np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]) < 0.5
    assert _angle_deg(np.linalg.inv(gt[-1]) @ est[-1]) < 1.0


def test_rgbd_on_a_generated_room_lap(generated_root: Path) -> None:
    from frontends.sources import make_source

    # One 5 m lap around the room centre, 150 frames at 320x240 (3.4 cm and 2.4 deg per frame).
    source = make_source(
        "generated", kind="rgbd", root=generated_root, num_frames=150, width=320, height=240
    )
    odometry = make_odometry("rgbd")
    est = np.stack([odometry.register(frame).T_W_S for frame in source])
    gt = np.linalg.inv(source.gt_poses[0]) @ source.gt_poses
    # Measured: ATE 5 mm, end-point error 1.8 cm, no failure.
    assert odometry.downscale == 1  # chosen automatically for 320-pixel-wide images
    assert ate_rmse(est, gt) < 0.02
    assert np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]) < 0.05
    assert odometry.num_failures == 0


def test_rgbd_odometry_covariance_grows_along_the_chain(generated_root: Path) -> None:
    """The motion covariance handed to the pose graph is positive definite and grows with the
    number of registrations chained since the previous anchor."""
    from frontends.sources import make_source

    source = make_source(
        "generated",
        kind="rgbd",
        root=generated_root,
        num_frames=150,
        width=320,
        height=240,
        frames=slice(0, 31),
    )
    odometry = make_odometry("rgbd")
    covariances = {}
    for frame in source:
        result = odometry.register(frame)
        if frame.index in (0, 5, 30):
            covariances[frame.index] = result.covariance
            odometry.restart_covariance()  # as the pipeline does at a new anchor
    short, long = covariances[5], covariances[30]
    for cov in (short, long):
        assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.trace(long[3:, 3:]) > 2 * np.trace(short[3:, 3:])
    # Frames rendered without normals cannot be evaluated: the pose graph's sigmas apply.
    plain = RgbdOdometry(downscale=1)
    plain.register(_render(_room(), T_W_C0, 0))
    assert plain.register(_render(_room(), T_W_C0 @ _se3(t=(0.01, 0.0, 0.0)), 1)).covariance is None
