"""Keyframing: when a submap closes, and how its points are gathered."""

from __future__ import annotations

import numpy as np
import pytest

from common.geometry import so3_exp, transform_points
from common.voxel_keys import KEY_LIMIT
from common.voxel_keys import point_voxel_keys as voxel_keys
from frontends.frame import Frame, point_ranges_m
from slam.algorithm.submaps import (
    KeyframeDecisions,
    Keyframer,
    SubmapConfig,
    SubmapPoints,
)
from slam.algorithm.voxel_grid import (
    DENSE_GROUPING_CELLS_PER_POINT,
    voxel_downsample,
    voxel_groups,
)


def _wall_view(index: int, half_width_m: float = 0.5) -> Frame:
    """A sensor 2 m in front of a wall (z = 2 in the sensor frame), seeing a 1 m x 1 m patch."""
    u = np.linspace(-half_width_m, half_width_m, 60)
    x, y = np.meshgrid(u, u)
    points = np.c_[x.ravel(), y.ravel(), np.full(x.size, 2.0)]
    normals = np.tile([0.0, 0.0, -1.0], (len(points), 1))
    return Frame(index=index, timestamp=0.1 * index, points=points, normals=normals)


def _pose(x_m: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x_m
    return T


def _closing_frames(cfg: SubmapConfig, step_m: float, frames: int) -> list[int]:
    keyframer = Keyframer(cfg)
    closed_at = []
    for i in range(frames):
        closed, _, _ = keyframer.add(_wall_view(i), _pose(step_m * i))
        if closed is not None:
            closed_at.append(i)
    return closed_at


def _cfg(**kw) -> SubmapConfig:
    base = {"max_distance_m": 100.0, "max_rotation_deg": 90.0, "max_range_m": 10.0}
    return SubmapConfig(**(base | kw))


def test_a_lingering_sensor_is_not_stored_again_and_again() -> None:
    """A frame count closes a static sensor's submap every max_frames frames (each one a copy
    of the same view); closing by covered surface keeps one submap."""
    assert _closing_frames(_cfg(max_frames=10), step_m=0.0, frames=45) == [10, 20, 30, 40]
    by_surface = _cfg(max_frames=1000, max_surface_views=2.0)
    assert _closing_frames(by_surface, step_m=0.0, frames=45) == []


def test_a_sweeping_sensor_closes_once_it_covers_the_surface_budget() -> None:
    # 5 cm per frame along a wall seen 1 m wide: the submap covers 2 views after ~20 frames
    closed_at = _closing_frames(_cfg(max_frames=1000, max_surface_views=2.0), 0.05, 80)
    assert 2 <= len(closed_at) <= 5
    gaps = np.diff([0, *closed_at])
    assert (gaps >= 15).all() and (gaps <= 25).all()
    # a larger budget gives proportionally longer submaps
    longer = _closing_frames(_cfg(max_frames=1000, max_surface_views=3.0), 0.05, 80)
    assert len(longer) < len(closed_at)


def _reference_downsample(voxel_size_m: float, points: np.ndarray, normals: np.ndarray):
    """The sorting implementation the keyframer used before counting into cells."""
    _, inverse, counts = np.unique(
        voxel_keys(points, voxel_size_m), return_inverse=True, return_counts=True
    )
    means = []
    for array in (points, normals):
        sums = [np.bincount(inverse, weights=array[:, k]) for k in range(3)]
        means.append(np.stack(sums, axis=1) / counts[:, None])
    return means


@pytest.mark.parametrize(
    ("spread_m", "voxel_size_m", "dense"),
    [(10.0, 0.35, True), (2.0, 0.05, True), (300.0, 0.05, False), (1e5, 0.35, False)],
)
def test_voxel_grouping_equals_sorting_the_voxel_keys(spread_m, voxel_size_m, dense) -> None:
    rng = np.random.default_rng(7)
    points = rng.uniform(-spread_m, spread_m, size=(20_000, 3))
    points[:, 2] *= 0.1  # flat, like a scan
    # points on cell borders and duplicates
    points[:100] = np.round(points[:100] / voxel_size_m) * voxel_size_m
    points[100:200] = points[:100]
    low = np.floor(points.min(axis=0) / voxel_size_m)
    cells = np.prod(np.floor(points.max(axis=0) / voxel_size_m) - low + 1)
    assert (cells <= DENSE_GROUPING_CELLS_PER_POINT * len(points)) == dense  # both ways tested

    inverse, counts = voxel_groups(points, voxel_size_m)
    _, ref_inverse, ref_counts = np.unique(
        voxel_keys(points, voxel_size_m), return_inverse=True, return_counts=True
    )
    assert np.array_equal(inverse, ref_inverse.ravel())
    assert np.array_equal(counts, ref_counts)

    normals = rng.normal(size=points.shape)
    means, mean_normals = voxel_downsample(voxel_size_m, points, normals)
    ref_means, ref_normals = _reference_downsample(voxel_size_m, points, normals)
    np.testing.assert_allclose(means, ref_means, rtol=0, atol=1e-9)
    np.testing.assert_allclose(mean_normals, ref_normals, rtol=0, atol=1e-9)
    keys = voxel_keys(means, voxel_size_m)  # every output point is in its own voxel
    assert len(np.unique(keys)) == len(means)
    assert np.array_equal(keys, np.unique(voxel_keys(points, voxel_size_m)))


def test_voxel_grouping_beyond_the_key_range_raises() -> None:
    # 1e6 m at 0.35 m is ~2.9e6 voxels from the origin: keys would collide (they used to be
    # clipped silently, merging every far point into one voxel)
    points = np.array([[0.0, 0.0, 0.0], [1e6, 0.0, 0.0], [1e6, 1.0, 0.0]])
    with pytest.raises(ValueError, match=f"beyond \\+-{KEY_LIMIT - 1}"):
        voxel_groups(points, 0.35)
    with pytest.raises(ValueError, match="larger voxel size"):
        voxel_downsample(0.35, points)
    # the same points far from the origin but a few voxels apart fit a coarser grid
    assert len(voxel_groups(points, 10.0)[1]) == 2


def test_averaging_differs_from_kiss_icps_first_point_per_voxel() -> None:
    from kiss_icp.voxelization import voxel_down_sample

    rng = np.random.default_rng(5)
    points = rng.uniform(0.0, 4.0, size=(5000, 3))
    (means,) = voxel_downsample(1.0, points)
    firsts = voxel_down_sample(points, 1.0)
    assert len(means) == len(firsts) == 64
    # the same voxels, but means sit near the voxel centres and first points anywhere in them
    key_order = np.argsort(voxel_keys(firsts, 1.0))
    assert np.array_equal(voxel_keys(means, 1.0), voxel_keys(firsts, 1.0)[key_order])
    offset = np.abs(means - (np.floor(means) + 0.5)).max(axis=1)
    assert offset.max() < 0.2 and np.median(np.abs(firsts % 1.0 - 0.5).max(axis=1)) > 0.3


def test_keyframer_keeps_points_within_the_range_limits_inclusive() -> None:
    cfg = _cfg(min_range_m=1.0, max_range_m=5.0, map_voxel_m=0.01)
    # ranges 0.5, 1, 3, 5, 5 + 1e-9 and 7 m, exact in floating point
    points = np.array(
        [[0.5, 0, 0], [0, 1, 0], [1, 2, 2], [0, 0, 5], [0, 5 + 1e-9, 0], [-7, 0, 0]], dtype=float
    )
    keyframer = Keyframer(cfg)
    keyframer.add(Frame(index=0, timestamp=0.0, points=points), np.eye(4))
    kept = np.concatenate([chunk[0] for chunk in keyframer.points._near._parts])
    expected = points[1:4]
    order = np.argsort(voxel_keys(expected, cfg.map_voxel_m))
    np.testing.assert_allclose(kept, expected[order], atol=1e-12)


def test_a_scan_is_averaged_over_the_voxels_of_the_anchor_frame() -> None:
    rng = np.random.default_rng(11)
    cfg = _cfg(min_range_m=1.0, max_range_m=20.0, map_voxel_m=0.35)
    scans = [rng.uniform(-25.0, 25.0, size=(30_000, 3)) for _ in range(2)]
    T_A_S = np.eye(4)
    T_A_S[:3, :3] = [[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]]
    T_A_S[:3, 3] = [3.0, -1.0, 0.2]
    keyframer = Keyframer(cfg)
    keyframer.add(Frame(index=0, timestamp=0.0, points=scans[0]), np.eye(4))
    keyframer.add(Frame(index=1, timestamp=0.1, points=scans[1]), T_A_S)
    for (points_A, _, viewpoint_A), scan, T in zip(
        keyframer.points._near._parts, scans, [np.eye(4), T_A_S], strict=True
    ):
        ranges = np.linalg.norm(scan, axis=1)
        in_range = scan[(ranges >= 1.0) & (ranges <= 20.0)]
        (expected,) = voxel_downsample(0.35, transform_points(T, in_range))
        np.testing.assert_allclose(points_A, expected, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(viewpoint_A, np.tile(T[:3, 3], (len(expected), 1)))


def test_point_ranges_are_the_euclidean_norms_of_the_rows() -> None:
    points = np.random.default_rng(3).normal(scale=40.0, size=(5000, 3))
    points[0] = [3.0, 4.0, 12.0]
    ranges = point_ranges_m(points)
    assert ranges.shape == (5000,) and ranges[0] == 13.0
    np.testing.assert_allclose(ranges, np.linalg.norm(points, axis=1), rtol=1e-15)


def test_points_absorbed_after_every_decision_give_the_same_submaps() -> None:
    """Without a surface budget the keyframer decides from poses alone, so the points can be
    absorbed later (the pipeline's submap worker): deciding every frame first and absorbing
    afterwards closes the same submaps with the same points, normals and loop clouds."""
    cfg = _cfg(max_distance_m=0.3, map_voxel_m=0.05, loop_voxel_m=0.1)
    views = [_wall_view(i, half_width_m=0.5 + 0.01 * i) for i in range(20)]
    # LiDAR-like frames (no normals: the keyframer estimates them when a submap closes)
    views = [Frame(index=v.index, timestamp=v.timestamp, points=v.points) for v in views]
    frames = [(view, _pose(0.07 * view.index)) for view in views]
    at_once, lagged = Keyframer(cfg), Keyframer(cfg)
    assert lagged.decides_from_poses
    expected = [closed for frame, T in frames if (closed := at_once.add(frame, T)[0])]
    expected.append(at_once.finish())
    steps = [lagged.decisions.decide(frame, T) for frame, T in frames]
    got = [
        closed
        for step, (frame, _) in zip(steps, frames, strict=True)
        if (closed := lagged.points.absorb(step, frame))
    ]
    final = lagged.decisions.decide_finish()
    assert final is not None
    got.append(lagged.points.absorb(final, None))
    assert len(expected) >= 3
    assert [r.frame_indices for r in got] == [r.frame_indices for r in expected]
    for a, b in zip(got, expected, strict=True):
        for name in ("points_A", "normals_A", "loop_points_A"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not Keyframer(_cfg(max_surface_views=2.0)).decides_from_poses


def test_points_beyond_the_loop_range_are_mapped_but_left_out_of_the_loop_cloud() -> None:
    """``loop_max_range_m`` keeps the loop cloud of a longer map range as it was: the same as a
    keyframer whose range ends there, while the map points hold the farther points too."""
    rng = np.random.default_rng(5)
    # the ground 2 m below the sensor, to 60 m on either side
    scans = [
        np.c_[rng.uniform(-60.0, 60.0, size=(20_000, 2)), np.full(20_000, -2.0)] for _ in range(6)
    ]
    frames = [
        (Frame(index=i, timestamp=0.1 * i, points=scan), _pose(0.5 * i))
        for i, scan in enumerate(scans)
    ]
    common = {"max_distance_m": 100.0, "map_voxel_m": 0.5, "loop_voxel_m": 1.0}
    near_only = Keyframer(_cfg(max_range_m=30.0, **common))
    split = Keyframer(_cfg(max_range_m=80.0, loop_max_range_m=30.0, **common))
    coarse = Keyframer(_cfg(max_range_m=80.0, loop_max_range_m=30.0, far_map_voxel_m=2.0, **common))
    for frame, T in frames:
        for keyframer in (near_only, split, coarse):
            keyframer.add(frame, T)
    expected, got, coarse_far = near_only.finish(), split.finish(), coarse.finish()
    np.testing.assert_array_equal(got.loop_points_A, expected.loop_points_A)
    np.testing.assert_array_equal(coarse_far.loop_points_A, expected.loop_points_A)
    assert len(got.points_A) > 1.5 * len(expected.points_A)
    assert np.linalg.norm(got.points_A, axis=1).max() > 50.0
    assert np.linalg.norm(expected.points_A, axis=1).max() < 35.0
    # far points on a 2 m grid instead of 0.5 m: about 1/16 as many on a surface, far fewer here
    far = np.linalg.norm(got.points_A, axis=1) > 31.0
    coarse_far_rows = np.linalg.norm(coarse_far.points_A, axis=1) > 31.0
    assert 0 < coarse_far_rows.sum() < 0.5 * far.sum()


def _closed_submap(cfg: SubmapConfig, views: list[Frame], for_map: bool):
    decisions, points = KeyframeDecisions(cfg), SubmapPoints(cfg, for_map)
    for view in views:
        points.absorb(decisions.decide(view, _pose(0.05 * view.index)), view)
    final = decisions.decide_finish()
    assert final is not None
    return points.absorb(final, None)


def test_a_localisation_only_submap_keeps_its_points_without_normals() -> None:
    """A localisation-only run registers a LiDAR submap's points alone: on its own grid (the
    map's here) and without normal estimation the closed submap covers every voxel the map's
    submap covers, and the same loop voxels, with one point a voxel and none with a normal."""
    cfg = _cfg(max_distance_m=1.0, map_voxel_m=0.05, loop_voxel_m=0.1)
    views = [Frame(index=i, timestamp=0.1 * i, points=_wall_view(i).points) for i in range(4)]
    mapped, located = (_closed_submap(cfg, views, for_map) for for_map in (True, False))
    assert len(mapped.points_A) > 400
    np.testing.assert_allclose(np.linalg.norm(mapped.normals_A, axis=1), 1.0)
    assert not np.any(located.normals_A)
    located_keys = voxel_keys(located.points_A, 0.05)
    assert len(np.unique(located_keys)) == len(located_keys)
    assert set(voxel_keys(mapped.points_A, 0.05)) <= set(located_keys)
    assert set(voxel_keys(located.loop_points_A, 0.1)) == set(voxel_keys(mapped.loop_points_A, 0.1))


def test_a_localisation_only_submap_is_averaged_on_its_own_grid() -> None:
    """A localisation-only submap is averaged on localise_voxel_m (never encoded, it needs no
    finer grid), near and far points alike, RGB-D normals still averaged (loop refinement uses
    them)."""
    cfg = _cfg(
        max_distance_m=1.0,
        map_voxel_m=0.02,
        loop_voxel_m=0.1,
        loop_max_range_m=2.5,
        localise_voxel_m=0.1,
    )
    views = [_wall_view(i, half_width_m=2.0) for i in range(4)]
    mapped, located = (_closed_submap(cfg, views, for_map) for for_map in (True, False))
    keys = voxel_keys(located.points_A, 0.1)
    assert len(np.unique(keys)) == len(keys)
    assert np.linalg.norm(located.points_A, axis=1).max() > 2.6  # far points are kept
    assert 0 < len(located.points_A) < len(mapped.points_A) / 5
    np.testing.assert_allclose(located.normals_A, np.tile([0.0, 0.0, -1.0], (len(keys), 1)))


def test_a_localisation_only_submap_takes_scans_where_the_sensor_moved_or_turned() -> None:
    """With localise_scan_spacing_m, once the run is placed, a localisation-only submap takes
    a frame's points only once the sensor moved that far, or turned localise_scan_turn_deg,
    since the last frame it took (its first frame always); otherwise every frame. Each frame
    sees one point at its own depth, so the depths kept tell which frames were taken."""
    turned = np.eye(4)
    turned[:3, :3] = so3_exp(np.radians([0.0, 0.0, 15.0]))
    poses = [_pose(0.05 * i) for i in range(10)] + [_pose(0.45) @ turned]

    def depths_kept(placed: bool = True, **spacing) -> set[float]:
        cfg = _cfg(map_voxel_m=0.01, localise_voxel_m=0.01, loop_voxel_m=0.1, **spacing)
        decisions, points = KeyframeDecisions(cfg), SubmapPoints(cfg, for_map=False)
        points.placed = placed
        for i, T_W_S in enumerate(poses):
            frame = Frame(index=i, timestamp=0.1 * i, points=np.array([[0.0, 0.0, 1 + 0.1 * i]]))
            points.absorb(decisions.decide(frame, T_W_S), frame)
        final = decisions.decide_finish()
        assert final is not None
        return set(np.round(points.absorb(final, None).points_A[:, 2], 6).tolist())

    every = {round(1 + 0.1 * i, 6) for i in range(11)}
    spacing = {"localise_scan_spacing_m": 0.12, "localise_scan_turn_deg": 10.0}
    assert depths_kept() == every
    assert depths_kept(placed=False, **spacing) == every  # not placed yet
    spaced = depths_kept(**spacing)
    assert spaced == {1.0, 1.3, 1.6, 1.9, 2.0}  # frames 0, 3, 6, 9 moved; frame 10 turned
