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
    weights = found.astype(np.float64)
    mean = np.einsum("nki,nk->ni", neighbours, weights) / np.maximum(count, 1)[:, None]
    centred = (neighbours - mean[:, None, :]) * weights[..., None]
    normals = smallest_eigenvectors(_covariances(centred))
    valid = count >= min_neighbours
    to_sensor = np.broadcast_to(np.asarray(viewpoints, dtype=np.float64), points.shape) - points
    flip = np.einsum("ni,ni->n", normals, to_sensor) < 0
    normals[flip] *= -1.0
    normals[~valid] = 0.0
    return normals, valid


def _covariances(centred: np.ndarray) -> np.ndarray:
    """(N, 3, 3) sums of outer products of (N, k, 3) centred neighbours (6 products, not an
    einsum over 9, which was slower than the eigen solver)."""
    cov = np.empty((len(centred), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.einsum("nk,nk->n", centred[..., i], centred[..., j])
    return cov


SMALLEST_EIGENVECTOR_MIN_SEPARATION = 1e-6
"""Closed-form eigenvectors are used where the smallest eigenvalue is at least this fraction of
the matrix scale below the middle one; the others (lines, isotropic blobs, empty neighbourhoods)
go to LAPACK."""


def smallest_eigenvectors(cov: np.ndarray) -> np.ndarray:
    """Unit eigenvector of the smallest eigenvalue of each symmetric (N, 3, 3) matrix.

    In closed form (trigonometric eigenvalues, then the largest cross product of two rows of
    ``cov - lambda I``), about 10x faster than ``np.linalg.eigh`` on 3x3 matrices; matrices
    whose two smallest eigenvalues are too close for that are handed to ``np.linalg.eigh``.
    Signs are arbitrary, as with ``eigh``.
    """
    n = len(cov)
    a, b, c = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    d, e, f = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    q = (a + b + c) / 3.0
    p1 = d * d + e * e + f * f
    p2 = (a - q) ** 2 + (b - q) ** 2 + (c - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    safe_p = np.where(p > 0, p, 1.0)
    ba, bb, bc = (a - q) / safe_p, (b - q) / safe_p, (c - q) / safe_p
    bd, be, bf = d / safe_p, e / safe_p, f / safe_p
    det = ba * (bb * bc - bf * bf) - bd * (bd * bc - bf * be) + be * (bd * bf - bb * be)
    phi = np.arccos(np.clip(0.5 * det, -1.0, 1.0)) / 3.0
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    middle = q + 2.0 * p * np.cos(phi - 2.0 * np.pi / 3.0)
    rows = cov - smallest[:, None, None] * np.eye(3)
    crosses = np.stack(
        [
            np.cross(rows[:, 0], rows[:, 1]),
            np.cross(rows[:, 0], rows[:, 2]),
            np.cross(rows[:, 1], rows[:, 2]),
        ],
        axis=1,
    )
    lengths = np.linalg.norm(crosses, axis=2)
    best = np.argmax(lengths, axis=1)
    vectors = crosses[np.arange(n), best]
    length = lengths[np.arange(n), best]
    scale = np.maximum(np.abs(q) * 3.0, 1e-300)
    separated = (middle - smallest) > SMALLEST_EIGENVECTOR_MIN_SEPARATION * scale
    good = separated & (length > 0) & np.isfinite(length)
    vectors[good] /= length[good, None]
    if not good.all():
        vectors[~good] = np.linalg.eigh(cov[~good])[1][:, :, 0]
    return vectors
