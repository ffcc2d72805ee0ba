"""Keyframe features for RGB-D loop closure (:mod:`slam.algorithm.loop_rgbd`): ORB keypoints
lifted with depth, and the depth agreement of two keyframes under a relative pose."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry import transform_points
from slam.algorithm.loop_refine import RefineCloud


@dataclass
class KeyframeFeatures:
    """ORB features of a keyframe with their back-projected 3D points.

    Attributes:
        pixels: (N, 2) float32 keypoint positions (x, y).
        descriptors: (N, 32) uint8 ORB descriptors.
        points_S: (N, 3) keypoints lifted with the depth image (NaN where depth is invalid).
        gray: (H, W) uint8 image.
        depth: (H, W) float32 depth in metres (0 = invalid).
        K: 3x3 camera matrix.
        cloud: the submap cloud for the dense refinement (None: no refinement possible).
    """

    pixels: np.ndarray
    descriptors: np.ndarray
    points_S: np.ndarray
    gray: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    cloud: RefineCloud | None = None


def to_gray(rgb: np.ndarray | None, depth: np.ndarray) -> np.ndarray:
    """A uint8 grey image (a depth rendering when there is no colour image)."""
    import cv2

    if rgb is None:
        scaled = np.clip(depth / max(float(np.nanmax(depth)), 1e-6) * 255.0, 0, 255)
        return np.nan_to_num(scaled).astype(np.uint8)
    if rgb.ndim == 2:
        return np.ascontiguousarray(rgb, dtype=np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2GRAY)


def lift_pixels(
    pixels: np.ndarray, depth: np.ndarray, K: np.ndarray, min_depth_m: float, max_depth_m: float
) -> np.ndarray:
    """Back-project pixel positions with the nearest depth value (NaN where invalid)."""
    h, w = depth.shape
    cols = np.clip(np.round(pixels[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.round(pixels[:, 1]).astype(int), 0, h - 1)
    z = depth[rows, cols].astype(np.float64)
    valid = np.isfinite(z) & (z >= min_depth_m) & (z <= max_depth_m)
    points = np.full((len(pixels), 3), np.nan)
    points[valid, 0] = (pixels[valid, 0] - K[0, 2]) * z[valid] / K[0, 0]
    points[valid, 1] = (pixels[valid, 1] - K[1, 2]) * z[valid] / K[1, 1]
    points[valid, 2] = z[valid]
    return points


def depth_agreement(
    reference: KeyframeFeatures, query: KeyframeFeatures, T_Sj_Si: np.ndarray, inlier_m: float
) -> tuple[float, float]:
    """How well the reference depth, moved into the query view by ``T_Sj_Si``, agrees.

    Every 4th reference depth pixel is lifted, moved and projected into the query image; among
    those that land on a valid query depth, returns the fraction whose depth differs by less than
    ``inlier_m`` and the median absolute difference (``(0, inf)`` without overlap).
    """
    depth = reference.depth[::4, ::4]
    rows, cols = np.nonzero(depth > 0)
    if len(rows) == 0:
        return 0.0, float("inf")
    z = depth[rows, cols].astype(np.float64)
    K = reference.K
    u, v = cols * 4.0, rows * 4.0
    points = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
    moved = transform_points(T_Sj_Si, points)
    front = moved[:, 2] > 1e-3
    moved = moved[front]
    Kq = query.K
    uq = np.round(Kq[0, 0] * moved[:, 0] / moved[:, 2] + Kq[0, 2]).astype(int)
    vq = np.round(Kq[1, 1] * moved[:, 1] / moved[:, 2] + Kq[1, 2]).astype(int)
    h, w = query.depth.shape
    inside = (uq >= 0) & (uq < w) & (vq >= 0) & (vq < h)
    observed = np.zeros(len(moved))
    observed[inside] = query.depth[vq[inside], uq[inside]]
    overlap = observed > 0
    if overlap.sum() < 50:
        return 0.0, float("inf")
    difference = np.abs(observed[overlap] - moved[overlap, 2])
    return float(np.mean(difference < inlier_m)), float(np.median(difference))
