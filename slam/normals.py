"""Normals of unorganised point clouds (LiDAR), by PCA over nearest neighbours.

RGB-D frames get their normals from the depth grid (``frontends.depth``); LiDAR scans are too
sparse across rings for that, so the keyframer estimates normals on the accumulated submap cloud,
where several scans fill the gaps, and orients each normal towards the sensor position it was
seen from.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def estimate_normals(
    points: np.ndarray,
    viewpoints: np.ndarray,
    num_neighbours: int = 12,
    max_radius_m: float | None = None,
    min_neighbours: int = 5,
) -> tuple[np.ndarray, np.ndarray]:
    """PCA normals oriented towards ``viewpoints``.

    Args:
        points: (N, 3) points.
        viewpoints: (N, 3) sensor position each point was observed from (same frame as points),
            or (3,) for a single sensor position.
        num_neighbours: neighbours (including the point) of the local plane fit.
        max_radius_m: neighbours farther than this are ignored; None = no limit.
        min_neighbours: points with fewer valid neighbours get no normal.

    Returns:
        ``(normals (N, 3), valid (N,) bool)``; invalid rows are zero.
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    normals = np.zeros((n, 3))
    valid = np.zeros(n, dtype=bool)
    k = min(num_neighbours, n)
    if n < max(3, min_neighbours):
        return normals, valid
    tree = cKDTree(points)
    upper = np.inf if max_radius_m is None else max_radius_m
    dist, idx = tree.query(points, k=k, distance_upper_bound=upper, workers=-1)
    dist = dist.reshape(n, k)
    idx = idx.reshape(n, k)
    found = np.isfinite(dist)
    count = found.sum(axis=1)
    idx = np.where(found, idx, np.arange(n)[:, None])
    neighbours = points[idx]  # (N, k, 3); missing neighbours repeat the point itself
    weights = found[..., None].astype(np.float64)
    mean = (neighbours * weights).sum(axis=1) / np.maximum(count, 1)[:, None]
    centred = (neighbours - mean[:, None, :]) * weights
    cov = np.einsum("nki,nkj->nij", centred, centred)
    _, vectors = np.linalg.eigh(cov)
    normals = vectors[:, :, 0]
    valid = count >= min_neighbours
    to_sensor = np.broadcast_to(np.asarray(viewpoints, dtype=np.float64), points.shape) - points
    flip = np.einsum("ni,ni->n", normals, to_sensor) < 0
    normals[flip] *= -1.0
    normals[~valid] = 0.0
    return normals, valid
