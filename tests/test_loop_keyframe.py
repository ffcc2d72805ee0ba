"""Keyframe refinement of RGB-D loop edges (``RgbdLoopConfig.keyframe_refine``).

A submap cloud is fused with the odometry poses of its frames, so odometry drift inside a
submap bends it; the ICP between two bent submaps then lands off the anchors' relative pose even
when it aligns the clouds well. The keyframe stage registers the two anchor keyframes' own depth
from there. Generated room, the loop pair of frames 2 and 236 (as in test_loop_closure.py).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from common.geometry import relative_motion, transform_points
from frontends.sources import make_source
from slam.algorithm.loops.config import RgbdLoopConfig
from slam.algorithm.loops.keyframes import compact_depth
from slam.algorithm.loops.rgbd_verify import RgbdVerifier

ROOM = {"kind": "rgbd", "num_frames": 240, "seed": 0, "width": 320, "height": 240}
REFERENCE, QUERY = 2, 236


@pytest.fixture(scope="module")
def room():
    return make_source("generated", **ROOM, loader_options={"depth_options": {"stride": 2}})


def _drifted_submap(source, anchor: int, frames: range, drift_deg: float, drift_m: float):
    """Points and normals of ``frames`` in the anchor frame, fused with poses that drift away
    from the ground truth linearly (a yaw and a sideways shift growing to the given values at
    the last frame): the odometry drift inside a submap."""
    gt = source.gt_poses
    points, normals = [], []
    for n, k in enumerate(frames):
        frame = source[k]
        share = n / max(len(frames) - 1, 1)
        drift = np.eye(4)
        drift[:3, :3] = Rotation.from_rotvec([0.0, np.radians(drift_deg) * share, 0.0]).as_matrix()
        drift[:3, 3] = [drift_m * share, 0.0, 0.0]
        T_A_S = drift @ np.linalg.inv(gt[anchor]) @ gt[k]
        points.append(transform_points(T_A_S, frame.points))
        normals.append(frame.normals @ T_A_S[:3, :3].T)
    return np.vstack(points), np.vstack(normals)


def _pair(verifier: RgbdVerifier, source, drift_deg: float, drift_m: float):
    ref_points, ref_normals = _drifted_submap(
        source, REFERENCE, range(REFERENCE, REFERENCE + 20, 2), drift_deg, drift_m
    )
    query_points, query_normals = _drifted_submap(
        source, QUERY, range(QUERY, QUERY - 20, -2), -drift_deg, -drift_m
    )
    reference = verifier.features(source[REFERENCE], ref_points, ref_normals)
    query = verifier.features(source[QUERY], query_points, query_normals)
    return reference, query


def _guess(truth: np.ndarray) -> np.ndarray:
    delta = np.eye(4)
    delta[:3, :3] = Rotation.from_rotvec(np.radians(1.5) * np.array([0.6, 0.0, 0.8])).as_matrix()
    delta[:3, 3] = [0.02, -0.015, 0.01]
    return truth @ delta


def test_keyframe_refinement_removes_the_submap_drift_from_the_edge(room):
    truth = np.linalg.inv(room.gt_poses[REFERENCE]) @ room.gt_poses[QUERY]
    errors = {}
    for keyframe_refine in (False, True):
        # The depth agreement check as loose as noisy real depth needs: on this noise-free room
        # it rejects the drifted submap edge (below), and the point here is the edge's pose.
        cfg = RgbdLoopConfig(
            keyframe_refine=keyframe_refine, min_depth_agreement=0.3, max_depth_residual_m=0.05
        )
        verifier = RgbdVerifier(cfg)
        reference, query = _pair(verifier, room, drift_deg=1.5, drift_m=0.02)
        accepted, reason, T, scores, covariance = verifier.verify_dense(
            reference, query, _guess(truth)
        )
        assert accepted, (keyframe_refine, reason, scores)
        assert covariance is not None
        errors[keyframe_refine] = relative_motion(truth, T)
    # The bent submaps pull the submap-level edge off; the keyframes' own depth does not.
    assert errors[False][0] > 0.01 or errors[False][1] > 0.5, errors
    assert errors[True][0] < 0.005 and errors[True][1] < 0.1, errors


def test_keyframe_refinement_keeps_a_loop_that_drifted_submaps_would_lose(room):
    """Default checks: the drifted submaps' edge fails the keyframe depth agreement, so without
    the keyframe stage the loop is lost; with it, the edge is corrected and accepted."""
    truth = np.linalg.inv(room.gt_poses[REFERENCE]) @ room.gt_poses[QUERY]
    plain = RgbdVerifier(RgbdLoopConfig(keyframe_refine=False))
    reference, query = _pair(plain, room, drift_deg=1.5, drift_m=0.02)
    accepted, reason, _, _, _ = plain.verify_dense(reference, query, _guess(truth))
    assert not accepted and "depth agreement" in reason, reason
    verifier = RgbdVerifier(RgbdLoopConfig())
    reference, query = _pair(verifier, room, drift_deg=1.5, drift_m=0.02)
    accepted, reason, T, scores, _ = verifier.verify_dense(reference, query, _guess(truth))
    assert accepted, (reason, scores)
    error_m, error_deg = relative_motion(truth, T)
    assert error_m < 0.005 and error_deg < 0.1
    assert scores["final_depth_agreement"] > 0.9


def _single_plane(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``depth`` with every pixel off its dominant plane set invalid (0)."""
    from frontends.depth import depth_to_points
    from frontends.frame import Intrinsics

    h, w = depth.shape
    cloud = depth_to_points(depth, Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h))
    # The most common normal direction (rounded) and, along it, the most common offset.
    keys, counts = np.unique(np.round(cloud.normals, 1), axis=0, return_counts=True)
    n0 = keys[np.argmax(counts)] / np.linalg.norm(keys[np.argmax(counts)])
    on_direction = cloud.normals @ n0 > 0.98
    offsets = cloud.points @ n0
    d0 = np.median(offsets[on_direction])
    keep = on_direction & (np.abs(offsets - d0) < 0.02)
    plane = np.zeros_like(depth)
    rows, cols = cloud.pixels[keep, 0], cloud.pixels[keep, 1]
    plane[rows, cols] = depth[rows, cols]
    return plane


def test_keyframe_refinement_rejects_keyframes_whose_depth_cannot_fix_the_pose(room):
    """The submap clouds register well, but the query keyframe's depth holds a single plane:
    its ICP cannot constrain the in-plane motion, so the keyframe stage rejects the edge instead
    of trusting it (the submap stage alone accepts the same pair)."""
    truth = np.linalg.inv(room.gt_poses[REFERENCE]) @ room.gt_poses[QUERY]
    results = {}
    for keyframe_refine in (False, True):
        # Every depth pixel: the plane covers a tenth of this small image.
        cfg = RgbdLoopConfig(keyframe_refine=keyframe_refine, keyframe_refine_stride_px=1)
        verifier = RgbdVerifier(cfg)
        reference, query = _pair(verifier, room, drift_deg=0.0, drift_m=0.0)
        query.depth = _single_plane(query.depth, query.K)
        assert np.count_nonzero(query.depth) > 1000
        results[keyframe_refine] = verifier.verify_dense(reference, query, _guess(truth))
    assert results[False][0], results[False][1:]
    accepted, reason, _, scores, covariance = results[True]
    assert covariance is None
    assert not accepted and reason.startswith("keyframe: degenerate"), (reason, scores)


def test_kept_keyframe_stores_depth_as_its_source_integers(room):
    """A kept keyframe holds its depth as the uint16 PNG units it was read from (grey uint8 +
    depth uint16: 3 bytes a pixel instead of 5), and gives back the float32 image bit for bit."""
    frame = room[REFERENCE]
    features = RgbdVerifier(RgbdLoopConfig()).features(frame)
    h, w = frame.depth.shape
    assert features.gray.dtype == np.uint8
    assert features.image_bytes <= 3 * h * w
    assert features.depth.dtype == np.float32
    assert np.array_equal(features.depth, frame.depth)


def test_compact_depth_is_exact_or_keeps_float32():
    rng = np.random.default_rng(0)
    raw = rng.integers(0, 8000, (48, 64)).astype(np.uint16)
    depth = raw.astype(np.float32) / np.float32(1000.0)
    stored, scale = compact_depth(depth, 1000.0)
    assert stored.dtype == np.uint16 and scale == 1000.0
    assert np.array_equal(stored.astype(np.float32) / np.float32(scale), depth)
    # depth that no integer image gives (rendered, noisy, NaN) stays float32, unchanged
    for other in (depth + np.float32(1e-4), np.where(raw > 7000, np.nan, depth), depth):
        kept, none = compact_depth(other, None if other is depth else 1000.0)
        assert kept.dtype == np.float32 and none is None
        assert np.array_equal(kept, other, equal_nan=True)


def test_loop_verifies_identically_from_compact_keyframes(room):
    """The whole verification (PnP, cv2.Odometry, submap and keyframe ICP, depth agreement) of
    the loop pair gives the same edge and scores from compact keyframes as from float32 ones."""
    verifier = RgbdVerifier(RgbdLoopConfig())
    results = []
    for compact in (True, False):
        reference, query = _pair(verifier, room, drift_deg=0.5, drift_m=0.005)
        assert reference.image_bytes < reference.gray.nbytes + 4 * reference.depth.size
        if not compact:  # the float32 images, as stored before
            reference.depth, query.depth = reference.depth.copy(), query.depth.copy()
            assert reference.image_bytes == reference.gray.nbytes + 4 * reference.depth.size
        matches = verifier.match(reference, query)
        results.append(verifier.verify(reference, query, matches))
    compact, plain = results
    assert compact.accepted, (compact.reason, compact.scores)
    assert compact.reason == plain.reason
    assert np.array_equal(compact.T_ref_query, plain.T_ref_query)
    assert compact.scores == plain.scores
