"""The shared leaf helpers: rigid transforms and packed voxel keys."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from common.geometry import (
    orthonormalize,
    rotation_angle_rad,
    so3_exp,
    transform_points,
)
from common.voxel_keys import KEY_LIMIT, pack_keys, point_voxel_keys, unpack_keys


def _random_pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.normal(scale=5.0, size=3)
    return T


def test_transform_points_matches_the_homogeneous_product() -> None:
    T = _random_pose(1)
    points = np.random.default_rng(2).normal(size=(500, 3))
    homogeneous = np.c_[points, np.ones(len(points))] @ T.T
    np.testing.assert_allclose(transform_points(T, points), homogeneous[:, :3], atol=1e-12)
    float32 = transform_points(T, points.astype(np.float32))
    np.testing.assert_allclose(float32, homogeneous[:, :3], atol=1e-5)
    assert transform_points(T, points[:0]).shape == (0, 3)


def test_orthonormalize_returns_the_nearest_rotation() -> None:
    T = _random_pose(3)
    perturbed = T.copy()
    perturbed[:3, :3] += np.random.default_rng(4).normal(scale=1e-3, size=(3, 3))
    perturbed[3] = [1e-9, 0.0, 0.0, 1.0]
    fixed = orthonormalize(perturbed)
    R = fixed[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    assert np.abs(R - T[:3, :3]).max() < 5e-3  # near the rotation it was perturbed from
    np.testing.assert_array_equal(fixed[3], [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_array_equal(fixed[:3, 3], T[:3, 3])
    assert perturbed[3, 0] == 1e-9  # the input is not modified
    reflection = np.diag([1.0, 1.0, -1.0, 1.0])
    assert np.linalg.det(orthonormalize(reflection)[:3, :3]) == pytest.approx(1.0)


def test_rotation_exp_and_angle() -> None:
    rotvec = np.array([0.3, -0.2, 0.5])
    R = so3_exp(rotvec)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-15)
    assert rotation_angle_rad(R) == pytest.approx(np.linalg.norm(rotvec), abs=1e-12)
    assert isinstance(rotation_angle_rad(R), float)
    stack = so3_exp(np.array([[0.0, 0.0, 0.1], [0.0, 2.0, 0.0]]))
    np.testing.assert_allclose(rotation_angle_rad(stack), [0.1, 2.0], atol=1e-12)
    assert rotation_angle_rad(np.eye(3)) == 0.0


def test_voxel_keys_round_trip_with_negative_coordinates() -> None:
    rng = np.random.default_rng(6)
    grid = rng.integers(-KEY_LIMIT + 1, KEY_LIMIT, size=(2000, 3))
    grid[:3] = [[-KEY_LIMIT + 1] * 3, [KEY_LIMIT - 1] * 3, [-1, 0, 1]]
    keys = pack_keys(grid)
    assert keys.dtype == np.int64
    np.testing.assert_array_equal(unpack_keys(keys), grid)
    # numeric order of the keys is the lexicographic order of (x, y, z)
    np.testing.assert_array_equal(np.argsort(keys, kind="stable"), np.lexsort(grid.T[::-1]))
    # torch tensors pack to the same keys
    keys_t = pack_keys(torch.from_numpy(grid))
    np.testing.assert_array_equal(keys_t.numpy(), keys)
    assert torch.equal(unpack_keys(keys_t), torch.from_numpy(grid))


@pytest.mark.parametrize("bad", [KEY_LIMIT, -KEY_LIMIT, np.iinfo(np.int64).min])
def test_voxel_keys_beyond_the_limit_raise(bad: int) -> None:
    grid = np.array([[0, 0, 0], [1, bad, 2]], dtype=np.int64)
    with pytest.raises(ValueError, match=f"beyond \\+-{KEY_LIMIT - 1}"):
        pack_keys(grid)
    with pytest.raises(ValueError, match="larger voxel size"):
        pack_keys(torch.from_numpy(grid))


def test_point_voxel_keys_floor_and_reject_far_or_nan_points() -> None:
    points = np.array([[0.05, -0.05, 0.0], [0.15, -0.15, 0.0]])
    np.testing.assert_array_equal(
        unpack_keys(point_voxel_keys(points, 0.1)), [[0, -1, 0], [1, -2, 0]]
    )
    with pytest.raises(ValueError):
        point_voxel_keys(np.array([[KEY_LIMIT * 0.1, 0.0, 0.0]]), 0.1)
    with pytest.raises(ValueError, match="NaN or infinite"):
        point_voxel_keys(np.array([[np.nan, 0.0, 0.0]]), 0.1)
