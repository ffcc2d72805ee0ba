"""Depth image -> 3D points with normals (and colours), the one place RGB-D frames are lifted.

Normals come from cross products of central differences on the depth grid: for pixel ``(v, u)``
with neighbours ``k`` pixels away, ``n = (P[v, u+k] - P[v, u-k]) x (P[v+k, u] - P[v-k, u])``,
oriented towards the sensor. A pixel is kept only when it and its four neighbours hold valid depth
and no neighbour lies across a depth discontinuity, which removes the "flying pixels" along object
silhouettes. Everything is vectorised numpy on (strided) views of the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from frontends.frame import Intrinsics


@dataclass(frozen=True)
class PointCloud:
    """Points lifted from one depth image, all in the camera frame (x right, y down, z forward).

    Attributes:
        points: (N, 3) float64 metres.
        normals: (N, 3) float64 unit normals pointing towards the camera.
        colors: (N, 3) uint8 RGB, or None when no image was given.
        pixels: (N, 2) int64 ``(row, col)`` of each point in the depth image.
    """

    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray | None
    pixels: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def depth_to_points(
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    *,
    rgb: np.ndarray | None = None,
    min_depth_m: float = 0.1,
    max_depth_m: float = 10.0,
    stride: int = 1,
    normal_step_px: int = 2,
    max_depth_jump: float = 0.05,
    max_points: int | None = None,
    seed: int = 0,
) -> PointCloud:
    """Back-project a depth image into points with normals.

    Args:
        depth_m: (H, W) depth along the optical axis in metres; 0, NaN, inf and values outside
            ``[min_depth_m, max_depth_m]`` are invalid.
        intrinsics: pinhole model of ``depth_m``; ``fy`` must be positive (sources normalise it).
        rgb: optional (H, W, 3) uint8 image on the same pixel grid, sampled into ``colors``.
        min_depth_m: nearest valid depth.
        max_depth_m: farthest valid depth.
        stride: keep every ``stride``-th pixel in both directions (1 = all).
        normal_step_px: pixel offset of the neighbours used for the normal (larger = smoother).
        max_depth_jump: a neighbour whose depth differs by more than this fraction of the
            centre depth marks a discontinuity; the pixel is dropped.
        max_points: if set, a seeded random subset of at most this many points is returned.
        seed: seed of that subset.

    Returns:
        The valid points; empty arrays when nothing is valid.
    """
    depth = np.asarray(depth_m)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth.shape}")
    if intrinsics.fy <= 0 or intrinsics.fx <= 0:
        raise ValueError("intrinsics must have fx > 0 and fy > 0; normalise the sign first")
    if stride < 1 or normal_step_px < 1:
        raise ValueError("stride and normal_step_px must be >= 1")
    height, width = depth.shape
    if rgb is not None and rgb.shape[:2] != depth.shape:
        raise ValueError(f"rgb {rgb.shape[:2]} and depth {depth.shape} must share a pixel grid")
    k = normal_step_px
    if height <= 2 * k or width <= 2 * k:
        return _empty(rgb is not None)

    z = depth.astype(np.float32, copy=False)
    with np.errstate(invalid="ignore"):
        valid_full = np.isfinite(z) & (z >= min_depth_m) & (z <= max_depth_m)
    z = np.where(valid_full, z, np.float32(0.0))

    rows = np.arange(k, height - k, stride)
    cols = np.arange(k, width - k, stride)
    # Same-length strided views of the centre and its four neighbours.
    center = (slice(k, height - k, stride), slice(k, width - k, stride))
    right = (center[0], slice(2 * k, width, stride))
    left = (center[0], slice(0, width - 2 * k, stride))
    down = (slice(2 * k, height, stride), center[1])
    up = (slice(0, height - 2 * k, stride), center[1])

    zc = z[center]
    valid = valid_full[center].copy()
    jump = np.float32(max_depth_jump) * zc
    for view in (right, left, down, up):
        valid &= valid_full[view]
        valid &= np.abs(z[view] - zc) <= jump
    if not valid.any():
        return _empty(rgb is not None)

    fx, fy, cx, cy = (
        np.float32(v) for v in (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
    )
    xn_c = (cols.astype(np.float32) - cx) / fx  # normalised image x of the centre columns
    yn_c = (rows.astype(np.float32) - cy) / fy
    step_x = np.float32(k) / fx
    step_y = np.float32(k) / fy

    # Tangents P_right - P_left and P_down - P_up on the grid, in float32 (enough for normals).
    z_r, z_l, z_d, z_u = z[right], z[left], z[down], z[up]
    xn = xn_c[None, :]
    yn = yn_c[:, None]
    az = z_r - z_l
    ax = xn * az + step_x * (z_r + z_l)
    ay = yn * az
    bz = z_d - z_u
    bx = xn * bz
    by = yn * bz + step_y * (z_d + z_u)
    nx = ay * bz - az * by
    ny = az * bx - ax * bz
    nz = ax * by - ay * bx
    length_sq = nx * nx + ny * ny + nz * nz
    # n . P has the sign of n . (xn, yn, 1) because z > 0; flip so that n . P < 0.
    sign = np.where(nx * xn + ny * yn + nz > 0, np.float32(-1.0), np.float32(1.0))
    valid &= length_sq > 1e-24
    flat = np.flatnonzero(valid)
    if max_points is not None and len(flat) > max_points:
        flat = np.sort(np.random.default_rng(seed).choice(flat, max_points, replace=False))
    normals = np.empty((len(flat), 3))
    normals[:, 0] = nx.ravel()[flat]
    normals[:, 1] = ny.ravel()[flat]
    normals[:, 2] = nz.ravel()[flat]
    normals *= (sign.ravel()[flat] / np.sqrt(length_sq.ravel()[flat].astype(np.float64)))[:, None]

    # Points in float64 from the original depth values (exact back-projection).
    pix_r = rows[flat // len(cols)]
    pix_c = cols[flat % len(cols)]
    zz = np.asarray(depth[pix_r, pix_c], dtype=np.float64)
    points = np.empty((len(zz), 3))
    points[:, 0] = (pix_c - intrinsics.cx) * zz / intrinsics.fx
    points[:, 1] = (pix_r - intrinsics.cy) * zz / intrinsics.fy
    points[:, 2] = zz

    colors = None if rgb is None else np.ascontiguousarray(rgb[pix_r, pix_c], dtype=np.uint8)
    pixels = np.stack([pix_r, pix_c], axis=1).astype(np.int64)
    return PointCloud(points=points, normals=normals, colors=colors, pixels=pixels)


def _empty(with_colors: bool) -> PointCloud:
    return PointCloud(
        points=np.zeros((0, 3)),
        normals=np.zeros((0, 3)),
        colors=np.zeros((0, 3), np.uint8) if with_colors else None,
        pixels=np.zeros((0, 2), np.int64),
    )
