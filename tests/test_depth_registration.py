"""The dense depth registration that judges RGB-D loop edges in benchmarks/bench_slam.py: two
depth images rendered from a known relative pose (a room with a box and a ball, no noise)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from benchmarks.harness.depth_registration import depth_fit, register_depth
from common.geometry import relative_motion

W, H = 320, 240
K = np.array([[262.5, 0.0, 159.5], [0.0, 262.5, 119.5], [0.0, 0.0, 1.0]])


def _se3(rotvec=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _scene() -> trimesh.Trimesh:
    walls = trimesh.creation.box(extents=(5.0, 4.0, 3.0))
    walls.invert()
    box = trimesh.creation.box(extents=(1.0, 0.8, 1.2))
    box.apply_transform(_se3((0.0, 0.0, 0.4), (0.9, 0.6, -0.9)))
    ball = trimesh.creation.icosphere(radius=0.5, subdivisions=3)
    ball.apply_translation((-1.0, -0.3, 0.1))
    return trimesh.util.concatenate([walls, box, ball])


def _depth(mesh: trimesh.Trimesh, T_W_C: np.ndarray) -> np.ndarray:
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    rays = np.stack([(u.ravel() - K[0, 2]) / K[0, 0], (v.ravel() - K[1, 2]) / K[1, 1]], 1)
    rays = np.hstack([rays, np.ones((u.size, 1))])
    dirs = (rays / np.linalg.norm(rays, axis=1, keepdims=True)) @ T_W_C[:3, :3].T
    origins = np.broadcast_to(T_W_C[:3, 3], dirs.shape)
    hits, index, _ = mesh.ray.intersects_location(origins, dirs, multiple_hits=False)
    depth = np.zeros(u.size)
    depth[index] = ((hits - T_W_C[:3, 3]) @ T_W_C[:3, :3])[:, 2]
    return depth.reshape(H, W).astype(np.float32)


# Reference camera 1 m from the room centre looking along +y (x right, y down, z forward); the
# query has moved and turned as much as a loop closure's anchors do (22 cm, 12 deg).
T_W_REF = _se3((-np.pi / 2, 0.0, 0.0), (0.2, -1.0, 0.1))
T_REF_QUERY = _se3((0.05, 0.2, -0.02), (0.15, -0.05, 0.15))


@pytest.fixture(scope="module")
def depths() -> tuple[np.ndarray, np.ndarray]:
    mesh = _scene()
    return _depth(mesh, T_W_REF), _depth(mesh, T_W_REF @ T_REF_QUERY)


@pytest.mark.parametrize(
    "start",
    [
        _se3(),  # the truth
        _se3((0.01, -0.025, 0.01), (0.03, 0.02, -0.02)),  # 4 cm / 1.6 deg off
        _se3((-0.02, 0.01, 0.0), (-0.02, -0.03, 0.03)),  # 4.7 cm / 1.3 deg off the other way
    ],
)
def test_recovers_a_known_pose_from_a_start_near_it(depths, start: np.ndarray) -> None:
    ref, query = depths
    result = register_depth(ref, query, K, T_REF_QUERY @ start)
    assert result.ok
    error_m, error_deg = relative_motion(T_REF_QUERY, result.T_ref_query)
    assert error_m < 0.003 and error_deg < 0.15, (error_m, error_deg)
    assert result.inlier_fraction > 0.95 and result.rmse_m < 0.005
    assert result.overlap > 5000


def test_measures_a_wrong_edge_as_off_by_its_error(depths) -> None:
    ref, query = depths
    wrong_edge = T_REF_QUERY @ _se3(t=(0.0, 0.05, 0.0))  # shifted 5 cm
    truth_m, _ = relative_motion(T_REF_QUERY, wrong_edge)
    assert truth_m == pytest.approx(0.05)
    # Registration starts from the (unknown to the edge) truth and judges the edge against itself.
    result = register_depth(ref, query, K, T_REF_QUERY)
    error_m, error_deg = relative_motion(result.T_ref_query, wrong_edge)
    assert error_m == pytest.approx(0.05, abs=0.003)
    assert error_deg < 0.15
    # ... and the edge's own fit is worse than the registration's (a 5 cm slide along the walls
    # keeps most pixels within 2 cm: the fit alone would not reveal it).
    edge_fraction, _, _ = depth_fit(ref, query, K, wrong_edge)
    assert edge_fraction < result.inlier_fraction - 0.05


def _edge(kept: bool, edge_vs_dense: list[float]) -> dict:
    return {
        "reference_submap": 0,
        "query_submap": 8,
        "reference_frame": 0,
        "query_frame": 240,
        "kept": kept,
        "baseline": [0.45, 21.0],
        "edge_vs_dense": edge_vs_dense,
        "edge_vs_gt": [0.025, 1.0],
        "dense_vs_gt": [0.023, 0.9],
        "dense_ok": True,
        "dense_rounds": 5,
        "dense_fit": [0.7, 0.009, 20000],
        "edge_fit": [0.7, 0.009, 20000],
        "gt_fit": [0.6, 0.01, 20000],
        "from_edge_vs_dense": [0.001, 0.05],
        "reverse_vs_dense": [0.005, 0.2],
        "from_identity_vs_dense": [0.45, 21.0],
    }


def test_report_counts_edges_beyond_the_dense_limit() -> None:
    from benchmarks.slam_tables import dense_section

    edges = [_edge(True, [0.004, 0.2]), _edge(True, [0.03, 0.3]), _edge(False, [0.01, 1.5])]
    lines = dense_section("7-Scenes", {"loop_dense": edges})
    summary = next(line for line in lines if line.startswith("| 7-Scenes |"))
    cells = [c.strip() for c in summary.strip("|").split("|")]
    assert cells[1:4] == ["3", "2", "3.00 / 0.30"]  # verified, kept, worst kept vs dense
    assert cells[5] == "2 / 1"  # beyond 2 cm / 1 deg: verified / kept
    assert sum(line.startswith("| 0 -> 8 (0, 240)") for line in lines) == 3
    assert dense_section("7-Scenes", {}) == []
