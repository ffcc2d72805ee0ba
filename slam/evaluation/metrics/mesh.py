"""Mesh accuracy / completion against a ground-truth surface.

Both meshes are sampled uniformly by area. The distance of a sample to the *other* surface is the
exact point-to-triangle distance to the best of a few candidate triangles, found through a KD-tree
on the other mesh's samples and face centroids (the triangles those nearest points lie on). This
is exact whenever the closest triangle is among the candidates and never smaller than the true
distance; its excess is bounded by the sample spacing and in practice micrometres (measured on
the Replica office0 mesh: mean excess 1e-8 m, max 3e-6 m, against brute force). It is much
faster than ``trimesh.proximity.closest_point`` and, unlike plain sample-to-sample distances,
gives ~0 for a perfect reconstruction.

Definitions (as in iMAP / NICE-SLAM, with point-to-surface distances):

- accuracy: mean distance from points on ``pred`` to the ``gt`` surface (metres);
- completion: mean distance from points on ``gt`` to the ``pred`` surface (metres);
- completion ratio: fraction of ``gt`` points whose distance is below ``threshold_m``.

An empty prediction (no faces) yields ``inf`` accuracy/completion and ratio 0 rather than an
exception, so that a run that produced nothing still writes its metrics; a warning is logged.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass

import numpy as np
import trimesh

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MeshMetrics:
    """Surface-distance metrics of a reconstruction against ground truth (distances in metres).

    Attributes:
        accuracy_m: mean distance pred -> gt.
        completion_m: mean distance gt -> pred.
        completion_ratio: fraction (0..1) of gt samples closer than ``threshold_m`` to pred.
        precision_ratio: fraction (0..1) of pred samples closer than ``threshold_m`` to gt.
        f_score: harmonic mean of precision and completion ratio (0..1).
        accuracy_median_m: median distance pred -> gt.
        completion_median_m: median distance gt -> pred.
        threshold_m: the distance threshold used for the ratios.
        num_samples: samples drawn on each mesh.
        num_pred_faces: faces of the prediction (0 when it was empty).
    """

    accuracy_m: float
    completion_m: float
    completion_ratio: float
    precision_ratio: float
    f_score: float
    accuracy_median_m: float
    completion_median_m: float
    threshold_m: float
    num_samples: int
    num_pred_faces: int

    def as_dict(self) -> dict[str, float | int]:
        """Plain dict (for ``metrics.json``)."""
        return asdict(self)


def surface_distances(
    points: np.ndarray,
    mesh: trimesh.Trimesh,
    *,
    num_reference_samples: int = 200_000,
    num_candidates: int = 16,
    seed: int = 0,
) -> np.ndarray:
    """Distance (metres) from each of ``points`` (N, 3) to the surface of ``mesh``.

    See the module docstring for how candidate triangles are chosen. Raises ``ValueError`` for a
    mesh without faces.
    """
    if len(mesh.faces) == 0:
        raise ValueError("surface_distances: the mesh has no faces")
    samples, face_index = trimesh.sample.sample_surface(mesh, num_reference_samples, seed=seed)
    return _distances_to_sampled_surface(
        np.asarray(points, dtype=np.float64), mesh, samples, face_index, num_candidates
    )


def _distances_to_sampled_surface(
    points: np.ndarray,
    mesh: trimesh.Trimesh,
    samples: np.ndarray,
    face_index: np.ndarray,
    num_candidates: int,
) -> np.ndarray:
    from scipy.spatial import cKDTree

    if len(points) == 0:
        return np.zeros(0)
    # Face centroids join the samples so that faces too small to receive a sample still become
    # candidates (otherwise a point on a small isolated part could be matched to a far surface).
    samples = np.concatenate([samples, mesh.triangles_center])
    face_index = np.concatenate([face_index, np.arange(len(mesh.faces))])
    k = max(1, min(num_candidates, len(samples)))
    tree = cKDTree(samples)
    _, nearest = tree.query(points, k=k, workers=-1)
    # Neighbouring samples often lie on one triangle (always on a coarse mesh): measure each
    # (point, triangle) pair once.
    candidates = np.sort(face_index[nearest.reshape(len(points), k)], axis=1)
    first = np.ones(candidates.shape, dtype=bool)
    first[:, 1:] = candidates[:, 1:] != candidates[:, :-1]
    rows = np.nonzero(first)[0]
    query = points[rows]
    closest = trimesh.triangles.closest_point(mesh.triangles[candidates[first]], query)
    distance = np.linalg.norm(closest - query, axis=1)
    # ``rows`` is sorted and holds every point at least once: the nearest of each point's run
    return np.minimum.reduceat(distance, np.searchsorted(rows, np.arange(len(points))))


def mesh_metrics(
    pred: trimesh.Trimesh,
    gt: trimesh.Trimesh,
    *,
    num_samples: int = 200_000,
    threshold_m: float = 0.05,
    seed: int = 0,
    gt_face_mask: np.ndarray | None = None,
    num_candidates: int = 16,
) -> MeshMetrics:
    """Accuracy, completion and completion ratio of ``pred`` against ``gt`` (both in metres).

    Args:
        pred: reconstructed mesh.
        gt: ground-truth mesh in the same frame.
        num_samples: points sampled uniformly by area on each mesh.
        threshold_m: distance below which a sample counts as reconstructed / correct.
        seed: sampling seed (results are deterministic for a given seed).
        gt_face_mask: optional (F_gt,) bool; only these gt faces are sampled for completion
            (e.g. from :func:`visible_face_mask`, to ignore parts the sensor never saw). Accuracy
            is always measured against the whole gt surface.
        num_candidates: candidate triangles per query (see module docstring).

    Returns:
        :class:`MeshMetrics`. An empty ``pred`` gives ``inf`` distances and zero ratios.

    Raises:
        ValueError: ``gt`` has no faces, or ``gt_face_mask`` has the wrong shape or keeps nothing.
    """
    if len(gt.faces) == 0:
        raise ValueError("mesh_metrics: the ground-truth mesh has no faces")
    gt_samples, gt_faces = trimesh.sample.sample_surface(gt, num_samples, seed=seed)
    if gt_face_mask is None:
        gt_eval_samples = gt_samples
    else:
        mask = np.asarray(gt_face_mask, dtype=bool)
        if mask.shape != (len(gt.faces),):
            raise ValueError(
                f"mesh_metrics: gt_face_mask has shape {mask.shape}, expected ({len(gt.faces)},)"
            )
        if not mask.any():
            raise ValueError("mesh_metrics: gt_face_mask keeps no face of the ground-truth mesh")
        weights = gt.area_faces * mask
        gt_eval_samples, _ = trimesh.sample.sample_surface(
            gt, num_samples, face_weight=weights, seed=seed + 1
        )

    if len(pred.faces) == 0 or pred.area <= 0.0:
        logger.warning("mesh_metrics: the predicted mesh is empty; reporting infinite distances")
        return MeshMetrics(
            accuracy_m=math.inf,
            completion_m=math.inf,
            completion_ratio=0.0,
            precision_ratio=0.0,
            f_score=0.0,
            accuracy_median_m=math.inf,
            completion_median_m=math.inf,
            threshold_m=float(threshold_m),
            num_samples=int(num_samples),
            num_pred_faces=0,
        )

    pred_samples, pred_faces = trimesh.sample.sample_surface(pred, num_samples, seed=seed + 2)
    to_gt = _distances_to_sampled_surface(pred_samples, gt, gt_samples, gt_faces, num_candidates)
    to_pred = _distances_to_sampled_surface(
        gt_eval_samples, pred, pred_samples, pred_faces, num_candidates
    )
    precision = float(np.mean(to_gt < threshold_m))
    recall = float(np.mean(to_pred < threshold_m))
    f_score = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return MeshMetrics(
        accuracy_m=float(to_gt.mean()),
        completion_m=float(to_pred.mean()),
        completion_ratio=recall,
        precision_ratio=precision,
        f_score=float(f_score),
        accuracy_median_m=float(np.median(to_gt)),
        completion_median_m=float(np.median(to_pred)),
        threshold_m=float(threshold_m),
        num_samples=int(num_samples),
        num_pred_faces=len(pred.faces),
    )


def visible_face_mask(
    mesh: trimesh.Trimesh,
    T_W_C: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    *,
    max_depth_m: float = 10.0,
    min_depth_m: float = 0.05,
) -> np.ndarray:
    """Faces whose centroid lies inside the view frustum of at least one camera.

    A frustum test only (no occlusion): cheap, and enough to drop parts of a ground-truth model
    that the trajectory never looked at. Cameras follow the OpenCV convention (z forward).

    Args:
        mesh: mesh in the world frame.
        T_W_C: (M, 4, 4) camera-to-world poses.
        K: 3x3 camera matrix.
        width, height: image size in pixels.
        max_depth_m, min_depth_m: depth range counted as seen.

    Returns:
        (F,) bool mask.
    """
    poses = np.asarray(T_W_C, dtype=np.float64).reshape(-1, 4, 4)
    centroids = np.asarray(mesh.triangles_center, dtype=np.float64)
    seen = np.zeros(len(centroids), dtype=bool)
    for T in poses:
        R, t = T[:3, :3], T[:3, 3]
        p_C = (centroids - t) @ R  # R^T (p - t), row-vector form
        z = p_C[:, 2]
        in_range = (z > min_depth_m) & (z < max_depth_m)
        z_safe = np.where(in_range, z, 1.0)
        u = K[0, 0] * p_C[:, 0] / z_safe + K[0, 2]
        v = K[1, 1] * p_C[:, 1] / z_safe + K[1, 2]
        seen |= in_range & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return seen
