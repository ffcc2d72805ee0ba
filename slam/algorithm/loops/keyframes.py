"""Keyframe features for RGB-D loop closure (:mod:`slam.algorithm.loops.rgbd`): ORB keypoints
lifted with depth, and the depth agreement of two keyframes under a relative pose."""

from __future__ import annotations

import numpy as np

from common.geometry import transform_points
from slam.algorithm.loops.refine import RefineCloud


def compact_depth(depth: np.ndarray, scale: float | None) -> tuple[np.ndarray, float | None]:
    """A depth image as the integers it was read from, when that is exact: ``(uint16 raw,
    scale)`` such that ``raw.astype(float32) / float32(scale)`` equals ``depth`` bit for bit (the
    sources' own conversion, :func:`~frontends.sources._io.read_depth_png`), else ``(float32
    depth, None)``. Half the bytes of the float32 image for the image sources' depth."""
    depth = np.asarray(depth, dtype=np.float32)
    if scale is None or not scale > 0 or not np.isfinite(depth).all():
        return depth, None
    raw = np.rint(depth.astype(np.float64) * scale)
    if raw.min(initial=0.0) < 0 or raw.max(initial=0.0) > np.iinfo(np.uint16).max:
        return depth, None
    raw = raw.astype(np.uint16)
    if not np.array_equal(_expand_depth(raw, scale), depth):
        return depth, None
    return raw, float(scale)


def _expand_depth(raw: np.ndarray, scale: float) -> np.ndarray:
    return raw.astype(np.float32) / np.float32(scale)


class KeyframeFeatures:
    """ORB features of a keyframe with their back-projected 3D points.

    The loop detector keeps one per closed submap for the whole run, so its images are stored
    compactly: the depth as its source's uint16 integers where that is exact
    (:func:`compact_depth`); :attr:`depth` gives it back as the float32 image, bit for bit.

    Attributes:
        pixels: (N, 2) float32 keypoint positions (x, y).
        descriptors: (N, 32) uint8 ORB descriptors.
        points_S: (N, 3) keypoints lifted with the depth image (NaN where depth is invalid).
        gray: (H, W) uint8 image.
        depth: (H, W) float32 depth in metres (0 = invalid), decoded from the stored image.
        K: 3x3 camera matrix.
        cloud: the submap cloud for the dense refinement (None: no refinement possible).
    """

    __slots__ = ("K", "_depth", "_scale", "cloud", "descriptors", "gray", "pixels", "points_S")

    def __init__(
        self,
        pixels: np.ndarray,
        descriptors: np.ndarray,
        points_S: np.ndarray,
        gray: np.ndarray,
        depth: np.ndarray,
        K: np.ndarray,
        cloud: RefineCloud | None = None,
        depth_scale: float | None = None,
    ) -> None:
        self.pixels = pixels
        self.descriptors = descriptors
        self.points_S = points_S
        self.gray = np.ascontiguousarray(gray, dtype=np.uint8)
        self.K = K
        self.cloud = cloud
        self._depth, self._scale = compact_depth(depth, depth_scale)

    @property
    def depth(self) -> np.ndarray:
        """(H, W) float32 depth in metres (0 = invalid)."""
        if self._scale is None:
            return self._depth
        return _expand_depth(self._depth, self._scale)

    @depth.setter
    def depth(self, value: np.ndarray) -> None:
        self._depth, self._scale = np.asarray(value, dtype=np.float32), None

    @property
    def image_bytes(self) -> int:
        """Bytes of the stored images (grey and depth)."""
        return self.gray.nbytes + self._depth.nbytes


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
    query_depth = query.depth
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
    h, w = query_depth.shape
    inside = (uq >= 0) & (uq < w) & (vq >= 0) & (vq < h)
    observed = np.zeros(len(moved))
    observed[inside] = query_depth[vq[inside], uq[inside]]
    overlap = observed > 0
    if overlap.sum() < 50:
        return 0.0, float("inf")
    difference = np.abs(observed[overlap] - moved[overlap, 2])
    return float(np.mean(difference < inlier_m)), float(np.median(difference))
