"""Remapping (slam/algorithm/remap.py) on a real neural map: only submaps whose anchor moved past
a threshold are moved, the pass is recorded, and the map's voxels follow the moved submap."""

from __future__ import annotations

import numpy as np
import torch

from mapping.config import MapConfig
from mapping.networks import PriorModel
from mapping.neural_map import NeuralMap
from slam.algorithm.remap import RemapConfig, Remapper


def _plane(offset_x: float) -> tuple[np.ndarray, np.ndarray]:
    """A 1 m x 1 m patch of the plane z = 0 (anchor frame), normals up."""
    u, v = np.meshgrid(np.linspace(0.0, 1.0, 25), np.linspace(0.0, 1.0, 25))
    points = np.stack([u.ravel() + offset_x, v.ravel(), np.zeros(u.size)], axis=1)
    return points, np.tile([0.0, 0.0, 1.0], (len(points), 1))


def _translation(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def _map_with_two_submaps() -> tuple[NeuralMap, dict]:
    torch.manual_seed(0)
    cfg = MapConfig(voxel_size_m=0.2, min_points_per_voxel=1, device="cpu")
    neural_map = NeuralMap(cfg, PriorModel().eval())
    submaps = {}
    for submap_id, offset in ((0, 0.0), (1, 5.0)):
        submap = neural_map.encode(submap_id, *_plane(offset), np.eye(4))
        neural_map.fuse(submap)
        submaps[submap_id] = submap
    return neural_map, submaps


def test_only_anchors_that_moved_past_a_threshold_are_remapped() -> None:
    neural_map, submaps = _map_with_two_submaps()
    remapper = Remapper(RemapConfig(translation_threshold_m=0.01), neural_map)
    before = neural_map.voxel_centers()[0]
    poses = {0: _translation(0.004), 1: _translation(0.6), 7: _translation(3.0)}  # 7: no submap
    event = remapper.apply(submaps, poses, frame_index=42)
    assert event.moved_ids == [1] and event.num_checked == 2 and event.frame_index == 42
    assert np.isclose(event.max_translation_m, 0.6) and remapper.events == [event]
    np.testing.assert_array_equal(submaps[1].T_W_A, poses[1])
    np.testing.assert_array_equal(submaps[0].T_W_A, np.eye(4))  # under the threshold: left
    after = neural_map.voxel_centers()[0]
    # submap 1's voxels (x >= 4.6) moved 0.6 m along x (three voxels); submap 0's stayed
    assert after[:, 0].max() - before[:, 0].max() > 0.55
    assert np.isclose(after[:, 0].min(), before[:, 0].min())
    again = remapper.apply(submaps, poses, frame_index=43)  # already there: nothing to do
    assert again.moved_ids == [] and remapper.events == [event]


def test_a_disabled_remapper_moves_nothing() -> None:
    neural_map, submaps = _map_with_two_submaps()
    remapper = Remapper(RemapConfig(enabled=False), neural_map)
    event = remapper.apply(submaps, {1: _translation(1.0)}, frame_index=0)
    assert event.num_checked == 0 and event.moved_ids == [] and remapper.events == []
    np.testing.assert_array_equal(submaps[1].T_W_A, np.eye(4))
