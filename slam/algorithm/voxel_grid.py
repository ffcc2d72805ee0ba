"""Points averaged over the voxels of a grid: the voxel of every point, and voxel means.

Keyframing averages every scan and every submap this way, so the grouping avoids a sort where it
can (:func:`voxel_groups`).
"""

from __future__ import annotations

import numpy as np

from common.voxel_keys import KEY_LIMIT, point_voxel_keys

DENSE_GROUPING_CELLS_PER_POINT = 8
""":func:`voxel_groups` counts the points into the cells of their bounding box when it holds at
most this many cells per point (one KITTI scan within 30 m at 0.35 m: ~2), and sorts their keys
otherwise (counting costs about as much per cell as sorting per point)."""


def voxel_groups(points: np.ndarray, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The voxel of every point: ``(inverse, counts)``.

    Voxels are numbered in increasing :func:`~common.voxel_keys.point_voxel_keys` order, so
    this equals ``np.unique(point_voxel_keys(points, voxel_size_m), return_inverse=True,
    return_counts=True)[1:]``, and like it raises a ``ValueError`` for points beyond the range
    of voxel keys.
    Where the bounding box of the points holds few enough cells (one LiDAR scan, one submap) the
    points are counted into those cells in linear time instead of sorting their keys, which was
    the largest cost of keyframing a 126k-point scan.
    """
    return column_voxel_groups(np.asarray(points, dtype=np.float64).T, voxel_size_m)


def column_voxel_groups(columns: np.ndarray, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`voxel_groups` of points given as (3, N) coordinate rows."""
    scaled = np.divide(columns, voxel_size_m, order="C")
    grid = np.floor(scaled, out=scaled).astype(np.int64)
    low = [int(value) for value in grid.min(axis=1)]
    high = [int(value) for value in grid.max(axis=1)]
    dims = [h - lo + 1 for lo, h in zip(low, high, strict=True)]
    cells = dims[0] * dims[1] * dims[2]
    inside = min(low) > -KEY_LIMIT and max(high) < KEY_LIMIT
    if not inside or cells > DENSE_GROUPING_CELLS_PER_POINT * columns.shape[1]:
        _, inverse, counts = np.unique(
            point_voxel_keys(columns.T, voxel_size_m), return_inverse=True, return_counts=True
        )
        return inverse.ravel(), counts
    cell = grid[0] - low[0]
    cell *= dims[1]
    cell += grid[1] - low[1]
    cell *= dims[2]
    cell += grid[2] - low[2]
    cell_counts = np.bincount(cell, minlength=cells)
    occupied = np.flatnonzero(cell_counts > 0)  # a third of the cost on a boolean array
    voxel_of_cell = np.empty(cells, dtype=np.intp)
    voxel_of_cell[occupied] = np.arange(len(occupied))
    return voxel_of_cell[cell], cell_counts[occupied]


def voxel_downsample(
    voxel_size_m: float, points: np.ndarray, *attributes: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Average points (and per-point float attributes) over the voxels of a grid.

    Differs from ``kiss_icp.voxelization.voxel_down_sample`` on purpose: the mean of each voxel
    (less noise for the map and the normals), not its first point, and in key order.

    Returns ``(points, *attributes)`` with one row per occupied voxel, in increasing
    :func:`~common.voxel_keys.point_voxel_keys` order. An attribute that is the same for every
    row (a broadcast array, e.g. one viewpoint per frame) or all zero (LiDAR frames carry no
    normals) is not averaged: its mean is that row.
    """
    if len(points) == 0:
        return (points, *attributes)
    inverse, counts = voxel_groups(points, voxel_size_m)
    out = []
    for array in (points, *attributes):
        if array is not points and (array.strides[0] == 0 or not array.any()):
            out.append(np.repeat(np.asarray(array[:1], dtype=np.float64), len(counts), axis=0))
            continue
        columns = [
            np.bincount(inverse, weights=array[:, k], minlength=len(counts))
            for k in range(array.shape[1])
        ]
        out.append(np.stack(columns, axis=1) / counts[:, None])
    return tuple(out)
