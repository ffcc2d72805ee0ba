"""Place-recognition descriptors of submaps, kept in a session so that a later merge can find
where two runs meet without their raw data.

A descriptor is a set of ORB keypoints with their positions in the submap's anchor frame:

* LiDAR (:func:`bev_descriptor`): the descriptor map_closures matches (Gupta et al., ICRA 2024):
  ORB on a bird's-eye density image of the submap cloud, each keypoint at its metric ``(x, y, 0)``.
  map_closures' Python API exposes neither its keypoints nor the density image's metric origin,
  so the image is built here the same way (occupied columns per cell, normalised to uint8).
* RGB-D (:func:`keyframe_descriptor`): the anchor keyframe's ORB keypoints lifted with its depth.

Matching (:func:`match_places`): Lowe's ratio test on the Hamming distances, then a RANSAC rigid
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
    """Least-squares ``T`` with ``target ~ T source`` (Kabsch; yaw-only when planar)."""
    if planar:
        source, target = source[:, :2], target[:, :2]
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    H = (source - mu_s).T @ (target - mu_t)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    D = np.eye(len(mu_s))
    D[-1, -1] = d
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    k = len(mu_s)
    T[:k, :k] = R
    T[:k, 3] = mu_t - R @ mu_s
    return T


def match_places(
    reference: PlaceDescriptor,
    query: PlaceDescriptor,
    ratio: float = 0.8,
    inlier_m: float = 0.5,
    iterations: int = 300,
    seed: int = 0,
) -> tuple[np.ndarray | None, int]:
    """``(T_ref_query guess, RANSAC inliers)`` of two descriptors (``(None, 0)``: no match)."""
    import cv2

    if len(reference) < 3 or len(query) < 3:
        return None, 0
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(query.bits, reference.bits, k=2)
    good = [
        (m[0].trainIdx, m[0].queryIdx)
        for m in pairs
        if len(m) == 2 and m[0].distance < ratio * m[1].distance
    ]
    sample = 2 if query.planar else 3
    if len(good) < sample + 1:
        return None, 0
    index = np.array(good)
    ref = reference.positions_A[index[:, 0]].astype(np.float64)
    qry = query.positions_A[index[:, 1]].astype(np.float64)
    rng = np.random.default_rng(seed)
    best = np.zeros(len(index), dtype=bool)
    for _ in range(iterations):
        pick = rng.choice(len(index), sample, replace=False)
        T = _rigid_fit(qry[pick], ref[pick], query.planar)
        residual = np.linalg.norm(qry @ T[:3, :3].T + T[:3, 3] - ref, axis=1)
        inliers = residual < inlier_m
        if inliers.sum() > best.sum():
            best = inliers
    if best.sum() < sample + 1:
        return None, int(best.sum())
    return _rigid_fit(qry[best], ref[best], query.planar), int(best.sum())
