"""Map quality of a LiDAR map over the ground-truth surface its scans observed.

Observed surface: the ground-truth mesh is sampled uniformly by area (near the trajectory only);
a sample is *observed within L metres* when some scan point whose range is below ``L`` lies
within :data:`OBSERVED_DISTANCE_M` of it (scan points placed with the ground-truth poses,
averaged on a :data:`OBSERVED_POINT_VOXEL_M` grid first, which moves none by more than 1.7 cm).
The samples observed within ``L`` are the surface a map of those scans should hold.

Scores of a reconstructed mesh (already in the ground-truth frame) over one region (the scans of
a stretch, and a range limit ``L``):

- recall at ``t``: the fraction of observed samples closer than ``t`` to the mesh; completion:
  their mean distance to the mesh;
- precision at ``t``: the fraction of points sampled on the mesh closer than ``t`` to the
  ground-truth surface, over the mesh points within ``L`` of some sensor position of the region
  (a map built from farther points is not scored on what lies beyond the region); accuracy: their
  mean distance;
- F-score at ``t``: the harmonic mean of the two.

Distances to a surface are the exact point-to-triangle distances of
``slam.evaluation.metrics.mesh.surface_distances``. Against scan points alone (a real recording
without a ground-truth mesh), only the precision side means something: :func:`point_precision`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from slam.algorithm.voxel_grid import voxel_downsample

THRESHOLDS_M = (0.1, 0.2)
"""Distance thresholds of precision, recall and F-score."""
POINT_THRESHOLDS_M = (0.1, 0.2, 0.5)
"""Thresholds of the precision against scan points (:func:`point_precision`): 5-15k points per
MulRan keyframe leave gaps wider than 20 cm on the surface they sample."""
OBSERVED_DISTANCE_M = 0.1
"""A ground-truth sample within this of a scan point (in range) is observed."""
OBSERVED_POINT_VOXEL_M = 0.02
"""Scan points are averaged on this grid before the observed test."""
GT_SAMPLES_PER_M2 = 16.0
"""Density of the ground-truth samples (one per 25 cm square)."""
MAX_GT_SAMPLES = 10_000_000
REFERENCE_SAMPLES = 300_000
"""Samples of a surface whose triangles are the candidates of a distance to it."""
MAX_SCORED_SAMPLES = 50_000
"""Observed samples (and mesh samples) whose distances are computed, a seeded subset."""
REGION_MARGIN_M = 5.0
"""Ground truth farther than the largest range limit plus this from every sensor position is
left out before sampling."""


@dataclass
class ScanSet:
    """Scans in the ground-truth frame: their points (world) with their ranges."""

    points_W: np.ndarray
    ranges_m: np.ndarray


def scan_set(scans: list[np.ndarray], poses: np.ndarray, max_range_m: float) -> ScanSet:
    """Points of ``scans`` (sensor frame) within ``max_range_m``, placed by ``poses``."""
    points, ranges = [], []
    for scan, T in zip(scans, poses, strict=True):
        scan = np.asarray(scan, dtype=np.float64)
        r = np.linalg.norm(scan, axis=1)
        keep = r < max_range_m
        points.append(scan[keep] @ T[:3, :3].T + T[:3, 3])
        ranges.append(r[keep])
    return ScanSet(np.concatenate(points), np.concatenate(ranges))


def crop_to_region(gt: trimesh.Trimesh, positions_W: np.ndarray, radius_m: float):
    """The faces of ``gt`` that come within ``radius_m`` of a sensor position."""
    from scipy.spatial import cKDTree

    centres = np.asarray(gt.triangles_center)
    extent = np.linalg.norm(np.asarray(gt.triangles) - centres[:, None], axis=2).max(axis=1)
    nearest, _ = cKDTree(positions_W).query(centres, workers=-1)
    keep = nearest <= radius_m + extent
    return trimesh.Trimesh(gt.vertices, gt.faces[keep], process=False)


def gt_samples(gt_region: trimesh.Trimesh, seed: int = 0) -> np.ndarray:
    """Samples of the ground-truth surface, :data:`GT_SAMPLES_PER_M2` (at most
    :data:`MAX_GT_SAMPLES`)."""
    count = int(min(MAX_GT_SAMPLES, max(1000, gt_region.area * GT_SAMPLES_PER_M2)))
    return trimesh.sample.sample_surface(gt_region, count, seed=seed)[0]


def observed_mask(samples: np.ndarray, scans: ScanSet, range_m: float) -> np.ndarray:
    """Which ground-truth ``samples`` the ``scans`` observed within ``range_m``."""
    from scipy.spatial import cKDTree

    use = scans.ranges_m < range_m
    if not use.any():
        return np.zeros(len(samples), dtype=bool)
    (points,) = voxel_downsample(OBSERVED_POINT_VOXEL_M, scans.points_W[use])
    tree = cKDTree(points)
    return np.isfinite(tree.query(samples, distance_upper_bound=OBSERVED_DISTANCE_M, workers=-1)[0])


def _subset(points: np.ndarray, limit: int, seed: int) -> np.ndarray:
    if len(points) <= limit:
        return points
    return points[np.random.default_rng(seed).choice(len(points), limit, replace=False)]


def _mesh_samples_in_range(mesh, positions_W: np.ndarray, range_m: float) -> np.ndarray:
    """A seeded subset of points sampled on ``mesh`` within ``range_m`` of a sensor position."""
    from scipy.spatial import cKDTree

    points, _ = trimesh.sample.sample_surface(mesh, 4 * MAX_SCORED_SAMPLES, seed=2)
    near, _ = cKDTree(positions_W).query(points, distance_upper_bound=range_m, workers=-1)
    return _subset(points[np.isfinite(near)], MAX_SCORED_SAMPLES, 3)


def region_scores(
    mesh: trimesh.Trimesh,
    gt_region: trimesh.Trimesh,
    observed: np.ndarray,
    positions_W: np.ndarray,
    range_m: float,
) -> dict[str, float]:
    """Precision, recall and F-score at every :data:`THRESHOLDS_M`, accuracy and completion
    (metres) of ``mesh`` over one region (module docstring)."""
    from slam.evaluation.metrics.mesh import surface_distances

    observed = _subset(observed, MAX_SCORED_SAMPLES, 1)
    scores: dict[str, float] = {"observed_samples": float(len(observed))}
    if len(mesh.faces) == 0 or len(observed) == 0:
        for t in THRESHOLDS_M:
            scores.update({f"precision_{t:g}": 0.0, f"recall_{t:g}": 0.0, f"f_{t:g}": 0.0})
        return {**scores, "accuracy_m": float("inf"), "completion_m": float("inf")}
    points = _mesh_samples_in_range(mesh, positions_W, range_m)
    to_gt = surface_distances(points, gt_region, num_reference_samples=REFERENCE_SAMPLES)
    to_map = surface_distances(observed, mesh, num_reference_samples=REFERENCE_SAMPLES)
    for t in THRESHOLDS_M:
        precision = float(np.mean(to_gt < t)) if len(to_gt) else 0.0
        recall = float(np.mean(to_map < t))
        total = precision + recall
        scores[f"precision_{t:g}"] = precision
        scores[f"recall_{t:g}"] = recall
        scores[f"f_{t:g}"] = 0.0 if total == 0 else 2 * precision * recall / total
    scores["accuracy_m"] = float(to_gt.mean()) if len(to_gt) else float("inf")
    scores["completion_m"] = float(to_map.mean())
    return scores


def point_precision(
    mesh: trimesh.Trimesh, points_W: np.ndarray, positions_W: np.ndarray, range_m: float
) -> dict[str, float]:
    """Precision at every :data:`POINT_THRESHOLDS_M` and accuracy of ``mesh`` against scan points
    (no ground-truth surface): the distance of each mesh sample within ``range_m`` of a sensor
    position to the nearest scan point, an upper bound of its distance to the true surface
    where the points are sparse."""
    from scipy.spatial import cKDTree

    if len(mesh.faces) == 0:
        return {f"precision_{t:g}": 0.0 for t in POINT_THRESHOLDS_M} | {"accuracy_m": float("inf")}
    samples = _mesh_samples_in_range(mesh, positions_W, range_m)
    distance, _ = cKDTree(points_W).query(samples, workers=-1)
    scores = {f"precision_{t:g}": float(np.mean(distance < t)) for t in POINT_THRESHOLDS_M}
    return {**scores, "accuracy_m": float(distance.mean())}
