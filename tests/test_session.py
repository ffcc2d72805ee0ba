"""The session section of a map file: what a merge reads round-trips through ``map.npz``, frames'
anchor-relative poses compactly and far below a millimetre off, and an older layout is refused
with one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from mapping.config import MapConfig
from mapping.errors import MapFileError
from mapping.map_io import VERSION, load_map, load_session, save_map
from mapping.networks import PriorModel
from mapping.neural_map import NeuralMap
from slam.algorithm.graph.gravity import UpMeasurement
from slam.algorithm.loops.place import PlaceDescriptor
from slam.algorithm.merge.session import Edge, SessionRecord
from tests.helpers import written_before_version_5


def _random_pose(rng: np.random.Generator, reach_m: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    T[:3, 3] = rng.uniform(-reach_m, reach_m, 3)
    return T


def _session(rng: np.random.Generator, frames: int = 50, reach_m: float = 80.0) -> SessionRecord:
    node_ids = np.array([3, 7, 9])
    frame_submap = np.repeat(node_ids, [20, 20, frames - 40])
    frame_T_A_S = np.array([_random_pose(rng, reach_m) for _ in range(frames)])
    frame_T_A_S[[0, 20, 40]] = np.eye(4)
    cov = np.diag(rng.uniform(1e-6, 1e-4, 6))
    return SessionRecord(
        setup={"sensor": "rgbd", "dataset": "test"},
        node_ids=node_ids,
        T_W_A=np.array([_random_pose(rng, 100.0) for _ in node_ids]),
        odometry=[Edge(3, 7, _random_pose(rng, 1.0), cov), Edge(7, 9, _random_pose(rng, 1.0), cov)],
        loops=[Edge(3, 9, _random_pose(rng, 1.0), cov)],
        frame_submap=frame_submap,
        frame_T_A_S=frame_T_A_S,
        timestamps=1.7e9 + np.arange(frames) / 30.0,
        descriptors={
            int(n): PlaceDescriptor(
                rng.uniform(-3, 3, (40, 3)).astype(np.float32),
                rng.integers(0, 256, (40, 32), dtype=np.uint8),
                False,
            )
            for n in node_ids
        },
    )


def test_session_round_trip_keeps_what_a_merge_needs():
    rng = np.random.default_rng(0)
    session = _session(rng)
    header, arrays = session.to_arrays()
    back = SessionRecord.from_arrays(json.loads(json.dumps(header)), arrays)
    np.testing.assert_array_equal(back.node_ids, session.node_ids)
    np.testing.assert_array_equal(back.T_W_A, session.T_W_A)  # anchors stay float64
    for a, b in zip(back.odometry + back.loops, session.odometry + session.loops, strict=True):
        assert (a.i, a.j) == (b.i, b.j)
        np.testing.assert_array_equal(a.T_Ai_Aj, b.T_Ai_Aj)
    np.testing.assert_array_equal(back.frame_submap, session.frame_submap)
    np.testing.assert_array_equal(back.timestamps, session.timestamps)
    # frames' anchor-relative poses: 7 float32 per frame instead of 12 float64
    assert arrays["frame_pose_A_S"].dtype == np.float32
    assert arrays["frame_pose_A_S"].nbytes * 3 < len(session.frame_T_A_S) * 12 * 8
    R, R0 = back.frame_T_A_S[:, :3, :3], session.frame_T_A_S[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.tile(np.eye(3), (len(R), 1, 1)),
                               atol=1e-12)  # fmt: skip
    cos = (np.einsum("nij,nij->n", R, R0) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 1e-4
    # translations up to 80 m from the anchor: far below a millimetre
    assert np.abs(back.frame_T_A_S[:, :3, 3] - session.frame_T_A_S[:, :3, 3]).max() < 1e-5
    np.testing.assert_array_equal(back.frame_T_A_S[:, 3], np.tile([0, 0, 0, 1.0], (50, 1)))
    np.testing.assert_allclose(back.frame_poses(), session.frame_poses(), atol=1e-5)
    for n, d in session.descriptors.items():
        np.testing.assert_array_equal(back.descriptors[n].bits, d.bits)
        np.testing.assert_allclose(back.descriptors[n].positions_A, d.positions_A, atol=2e-3)


def test_up_directions_round_trip_and_are_optional():
    session = _session(np.random.default_rng(2))
    up_A = np.array([0.01, -0.02, 1.0]) / np.linalg.norm([0.01, -0.02, 1.0])
    information = np.diag([1e4, 2e4, 0.0])
    session.up = {7: UpMeasurement(up_A, information, 900)}
    header, arrays = session.to_arrays()
    back = SessionRecord.from_arrays(header, arrays)
    assert list(back.up) == [7]
    np.testing.assert_array_equal(back.up[7].up_A, up_A)
    np.testing.assert_array_equal(back.up[7].information_A, information)
    older = {k: v for k, v in arrays.items() if not k.startswith("up_")}
    assert SessionRecord.from_arrays(header, older).up == {}
    with pytest.raises(ValueError, match="up directions"):
        SessionRecord.from_arrays(header, {**arrays, "up_ids": np.array([5])})


def test_inconsistent_frame_poses_are_refused():
    header, arrays = _session(np.random.default_rng(1)).to_arrays()
    with pytest.raises(ValueError, match="frame_pose_A_S"):
        SessionRecord.from_arrays(
            header, {**arrays, "frame_pose_A_S": arrays["frame_pose_A_S"][1:]}
        )
    bad = arrays["frame_pose_A_S"].copy()
    bad[3, :4] = 0.0
    with pytest.raises(ValueError, match="invalid quaternions"):
        SessionRecord.from_arrays(header, {**arrays, "frame_pose_A_S": bad})
    with pytest.raises(ValueError, match=r"frame_pose_A_S.*expected \(50, 7\)"):
        SessionRecord.from_arrays(header, {**arrays, "frame_pose_A_S": np.zeros((50, 3, 4))})


def _model() -> PriorModel:
    torch.manual_seed(0)
    return PriorModel().eval()


def _saved_with_session(tmp_path: Path) -> Path:
    nm = NeuralMap(MapConfig(min_points_per_voxel=1, device="cpu"), _model())
    rng = np.random.default_rng(2)
    d = rng.normal(size=(1500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    submap = nm.encode(3, d * 0.3, d, np.eye(4))
    nm.fuse(submap)
    path = tmp_path / "map.npz"
    save_map(nm, path, [submap], session=_session(rng).to_arrays())
    return path


def test_older_session_layout_loads_as_a_map_but_is_refused(tmp_path: Path):
    path = _saved_with_session(tmp_path)
    header, _, arrays = load_session(path)
    assert header["version"] == VERSION and "frame_pose_A_S" in arrays
    _, submaps = load_map(path, _model())
    v4 = tmp_path / "v4.npz"  # version 5 changed only the map's arrays: the session merges
    written_before_version_5(path, v4, 4, submaps)
    assert load_session(v4)[2].keys() == arrays.keys()
    old = tmp_path / "v3.npz"  # the earlier layout: float64 3x4 frame poses
    written_before_version_5(path, old, 3, submaps)
    assert load_map(old, _model())[0].num_voxels > 0
    with pytest.raises(MapFileError, match=r"v3\.npz: map format version 3 .*slam\.run") as info:
        load_session(old)
    assert "\n" not in str(info.value)


def test_frame_poses_follow_the_run_setting():
    """A run that kept its frames rigid on their anchors is merged the same way; others spread
    the gap to the next anchor over the frames (the last submap has none and stays rigid)."""
    session = _session(np.random.default_rng(5))
    rigid = session.anchor_poses()
    rigid = np.array([rigid[int(s)] for s in session.frame_submap]) @ session.frame_T_A_S
    followed = session.frame_poses()
    assert np.abs(followed[1:40] - rigid[1:40]).max() > 1e-3
    np.testing.assert_allclose(followed[[0, 20]], rigid[[0, 20]], atol=1e-12)
    np.testing.assert_allclose(followed[40:], rigid[40:], atol=1e-12)
    session.setup["frames_follow_next_anchor"] = False
    np.testing.assert_allclose(session.frame_poses(), rigid, atol=1e-12)
