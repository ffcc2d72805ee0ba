"""Place-recognition descriptors of submaps, kept in a session so that a later merge can find
where two runs meet without their raw data.

A descriptor is a set of ORB keypoints with their positions in the submap's anchor frame:

* LiDAR (:func:`bev_descriptor`): the descriptor map_closures matches (Gupta et al., ICRA 2024):
  ORB on a bird's-eye density image of the submap cloud, each keypoint at its metric ``(x, y, 0)``.
  map_closures' Python API exposes neither its keypoints nor the density image's metric origin,
  so the image is built here the same way (occupied columns per cell, normalised to uint8).
* RGB-D (:func:`keyframe_descriptor`): the anchor keyframe's ORB keypoints lifted with its depth.

Matching (:func:`ratio_matches`): Lowe's ratio test on the Hamming distances, then a RANSAC rigid
fit of the matched positions (2D rotation about z plus xy translation for a planar LiDAR
descriptor, full 3D otherwise). The result is only a guess: a merge verifies it on surface points
decoded from the submaps' own neural maps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_MAX_KEYPOINTS = 400


@dataclass
class PlaceDescriptor:
    """ORB keypoints of one submap.

    Attributes:
        positions_A: (M, 3) float32 keypoint positions in the anchor frame (z = 0 when planar).
        bits: (M, 32) uint8 ORB descriptors.
        planar: a bird's-eye descriptor (its matches determine yaw and xy only).
    """

    positions_A: np.ndarray
    bits: np.ndarray
    planar: bool

    def __len__(self) -> int:
        return len(self.bits)


def _orb(image: np.ndarray, max_features: int):
    import cv2

    orb = cv2.ORB.create(nfeatures=max_features)
    keypoints, bits = orb.detectAndCompute(image, None)
    if bits is None or not keypoints:
        return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
    return np.array([kp.pt for kp in keypoints], dtype=np.float32), bits


def bev_descriptor(
    points_A: np.ndarray, resolution_m: float, max_features: int = _MAX_KEYPOINTS
) -> PlaceDescriptor:
    """ORB keypoints of the bird's-eye density image of a LiDAR submap cloud (z up)."""
    points = np.asarray(points_A, dtype=np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < 10:
        return PlaceDescriptor(np.zeros((0, 3), np.float32), np.zeros((0, 32), np.uint8), True)
    cells = np.floor(points[:, :2] / resolution_m).astype(np.int64)
    low = cells.min(axis=0)
    size = cells.max(axis=0) - low + 1
    image = np.zeros((int(size[1]), int(size[0])), np.float32)
    np.add.at(image, (cells[:, 1] - low[1], cells[:, 0] - low[0]), 1.0)
    image = np.clip(image / max(np.percentile(image[image > 0], 95), 1.0), 0.0, 1.0)
    pixels, bits = _orb(np.pad((255 * image).astype(np.uint8), 16), max_features)
    xy = (pixels - 16.0 + 0.5 + low[None, :]) * resolution_m
    positions = np.column_stack([xy, np.zeros(len(xy))]).astype(np.float32)
    return PlaceDescriptor(positions, bits, True)


def keyframe_descriptor(
    pixels: np.ndarray, bits: np.ndarray, points_A: np.ndarray, max_features: int = _MAX_KEYPOINTS
) -> PlaceDescriptor:
    """The anchor keyframe's ORB keypoints that have depth (``points_A`` NaN where none)."""
    del pixels  # the positions carry what a merge needs
    points_A = np.asarray(points_A, dtype=np.float64)
    valid = np.isfinite(points_A).all(axis=1)
    keep = np.flatnonzero(valid)[:max_features]  # ORB returns the strongest first
    return PlaceDescriptor(
        points_A[keep].astype(np.float32), np.asarray(bits, np.uint8)[keep].copy(), False
    )


def _rigid_fit(source: np.ndarray, target: np.ndarray, planar: bool) -> np.ndarray:
    """Least-squares ``T`` with ``target ~ T source`` (Kabsch; yaw-only when planar).

    ``source`` and ``target`` are ``(..., n, 3)``: leading axes fit many sets at once."""
    if planar:
        source, target = source[..., :2], target[..., :2]
    mu_s, mu_t = source.mean(axis=-2), target.mean(axis=-2)
    H = np.swapaxes(source - mu_s[..., None, :], -1, -2) @ (target - mu_t[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, -1, -2), np.swapaxes(U, -1, -2)
    d = np.sign(np.linalg.det(V @ Ut))
    D = np.broadcast_to(np.eye(H.shape[-1]), H.shape).copy()
    D[..., -1, -1] = np.where(d == 0, 1.0, d)
    R = V @ D @ Ut
    k = H.shape[-1]
    T = np.broadcast_to(np.eye(4), (*H.shape[:-2], 4, 4)).copy()
    T[..., :k, :k] = R
    T[..., :k, 3] = mu_t - (R @ mu_s[..., None])[..., 0]
    return T


def ratio_matches(
    reference: PlaceDescriptor, query: PlaceDescriptor, ratio: float = 0.8
) -> np.ndarray:
    """``(M, 2)`` (reference index, query index) of the matches passing Lowe's ratio test."""
    import cv2

    if len(reference) < 2 or len(query) < 1:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(query.bits, reference.bits, k=2)
    good = [
        (m[0].trainIdx, m[0].queryIdx)
        for m in pairs
        if len(m) == 2 and m[0].distance < ratio * m[1].distance
    ]
    return np.array(good, dtype=np.int64).reshape(-1, 2)


def fit_matches(
    reference: PlaceDescriptor,
    query: PlaceDescriptor,
    index: np.ndarray,
    inlier_m: float = 0.5,
    iterations: int = 300,
    seed: int = 0,
) -> tuple[np.ndarray | None, int]:
    """RANSAC rigid fit of matched positions (all hypotheses scored at once)."""
    sample = 2 if query.planar else 3
    if len(index) < sample + 1:
        return None, 0
    ref = reference.positions_A[index[:, 0]].astype(np.float64)
    qry = query.positions_A[index[:, 1]].astype(np.float64)
    rng = np.random.default_rng(seed)
    picks = np.argpartition(rng.random((iterations, len(index))), sample - 1, axis=1)[:, :sample]
    T = _rigid_fit(qry[picks], ref[picks], query.planar)  # (iterations, 4, 4)
    moved = np.einsum("hij,nj->hni", T[:, :3, :3], qry) + T[:, None, :3, 3]
    inliers = np.linalg.norm(moved - ref, axis=2) < inlier_m
    best = inliers[int(np.argmax(inliers.sum(axis=1)))]
    if best.sum() < sample + 1:
        return None, int(best.sum())
    return _rigid_fit(qry[best], ref[best], query.planar), int(best.sum())
