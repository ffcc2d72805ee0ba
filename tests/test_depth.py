"""frontends.depth.depth_to_points on synthetic depth images with known geometry."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.depth import depth_to_points
from frontends.frame import Intrinsics

K = Intrinsics(fx=525.0, fy=520.0, cx=319.5, cy=239.5, width=640, height=480)


def rays(intrinsics: Intrinsics) -> np.ndarray:
    """(H, W, 3) viewing rays with z = 1."""
    v, u = np.mgrid[0 : intrinsics.height, 0 : intrinsics.width].astype(np.float64)
    return np.stack(
        [(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones_like(u)],
        axis=-1,
    )


def plane_depth(normal: np.ndarray, offset: float) -> np.ndarray:
    """Depth image of the plane n . p = offset."""
    return (offset / (rays(K) @ normal)).astype(np.float32)


def test_fronto_parallel_plane_is_exact_and_faces_the_sensor():
    depth = np.full((K.height, K.width), 2.0, np.float32)
    cloud = depth_to_points(depth, K)
    assert len(cloud) > 0.95 * K.width * K.height
    np.testing.assert_allclose(cloud.points[:, 2], 2.0, atol=1e-6)
    r, c = cloud.pixels.T
    np.testing.assert_allclose(cloud.points[:, 0], (c - K.cx) * 2.0 / K.fx, atol=1e-6)
    np.testing.assert_allclose(cloud.points[:, 1], (r - K.cy) * 2.0 / K.fy, atol=1e-6)
    np.testing.assert_allclose(cloud.normals, np.tile([0.0, 0.0, -1.0], (len(cloud), 1)), atol=1e-5)
    assert cloud.points.dtype == np.float64 and cloud.normals.dtype == np.float64


def test_tilted_plane_points_on_plane_and_normals_match():
    normal = np.array([0.3, -0.4, 1.0])
    normal /= np.linalg.norm(normal)
    offset = 2.5
    depth = plane_depth(normal, offset).astype(np.float64)
    cloud = depth_to_points(depth, K, max_depth_m=20.0)
    assert len(cloud) > 0.9 * K.width * K.height
    np.testing.assert_allclose(cloud.points @ normal, offset, atol=1e-6)
    # The plane faces the sensor from the side where n . p < offset, i.e. normal -n here.
    cos = cloud.normals @ -normal
    assert cos.min() > 0.9999
    np.testing.assert_allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-9)
    assert np.all(np.einsum("ij,ij->i", cloud.normals, cloud.points) < 0)


def test_sphere_normals_are_radial_and_face_the_sensor():
    center, radius = np.array([0.2, -0.1, 3.0]), 1.0
    d = rays(K)
    # Nearest ray/sphere intersection: |t d - c|^2 = r^2.
    a = np.einsum("hwi,hwi->hw", d, d)
    b = -2.0 * d @ center
    c = center @ center - radius**2
    disc = b * b - 4 * a * c
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0.0)
    cloud = depth_to_points(t.astype(np.float32), K)
    assert len(cloud) > 1000
    radial = (cloud.points - center) / radius
    cos = np.einsum("ij,ij->i", cloud.normals, radial)
    assert np.median(cos) > 0.9999
    assert cos.min() > 0.99


def test_invalid_depth_values_are_dropped_with_their_neighbours():
    depth = np.full((K.height, K.width), 1.5, np.float32)
    depth[100, 200] = np.nan
    depth[300, 400] = np.inf
    depth[50, 60] = 0.0
    depth[400, 500] = -1.0
    depth[200, 300] = 50.0  # beyond max_depth_m
    cloud = depth_to_points(depth, K, max_depth_m=10.0)
    assert np.all(np.isfinite(cloud.points)) and np.all(np.isfinite(cloud.normals))
    np.testing.assert_allclose(cloud.points[:, 2], 1.5, atol=1e-6)
    kept = {tuple(p) for p in cloud.pixels}
    for bad in [(100, 200), (300, 400), (50, 60), (400, 500), (200, 300)]:
        assert bad not in kept
        assert (bad[0], bad[1] + 2) not in kept  # its neighbour's normal would use it


def test_depth_discontinuity_removes_flying_pixels():
    depth = np.full((K.height, K.width), 1.0, np.float32)
    depth[:, 320:] = 3.0
    cloud = depth_to_points(depth, K)
    z = cloud.points[:, 2]
    assert np.all((np.abs(z - 1.0) < 1e-6) | (np.abs(z - 3.0) < 1e-6))
    cols = cloud.pixels[:, 1]
    assert not np.any((cols >= 318) & (cols <= 321))
    np.testing.assert_allclose(cloud.normals[:, 2], -1.0, atol=1e-5)


def test_all_invalid_gives_empty_cloud():
    for value in (0.0, np.nan):
        cloud = depth_to_points(np.full((48, 64), value, np.float32), K, rgb=None)
        assert len(cloud) == 0 and cloud.points.shape == (0, 3) and cloud.normals.shape == (0, 3)


def test_colors_stride_and_subsampling():
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 255, (K.height, K.width, 3), dtype=np.uint8)
    depth = np.full((K.height, K.width), 2.0, np.float32)
    full = depth_to_points(depth, K, rgb=rgb)
    np.testing.assert_array_equal(full.colors, rgb[full.pixels[:, 0], full.pixels[:, 1]])
    strided = depth_to_points(depth, K, rgb=rgb, stride=4)
    assert np.all(strided.pixels % 4 == 2)  # offset normal_step_px=2, then every 4th pixel
    assert abs(len(strided) - len(full) / 16) < 0.02 * len(full) / 16 + 200
    sub_a = depth_to_points(depth, K, max_points=1000, seed=3)
    sub_b = depth_to_points(depth, K, max_points=1000, seed=3)
    assert len(sub_a) == 1000
    np.testing.assert_array_equal(sub_a.points, sub_b.points)


def test_rejects_negative_fy_and_mismatched_rgb():
    depth = np.full((K.height, K.width), 2.0, np.float32)
    flipped = Intrinsics(K.fx, -K.fy, K.cx, K.cy, K.width, K.height)
    with pytest.raises(ValueError, match="fy"):
        depth_to_points(depth, flipped)
    with pytest.raises(ValueError, match="pixel grid"):
        depth_to_points(depth, K, rgb=np.zeros((10, 10, 3), np.uint8))
