"""Checks that a converged LiDAR loop registration is the only good one, and that the graph agrees.

ICP converges to the nearest minimum of its cost. Along a street whose facades repeat (a regular
avenue, identical buildings, evenly spaced trees), or along a featureless stretch, the minimum one
period along the street scores almost as well as the true one: a generated street's start/end
closure converged 3.2 m along the street with inlier ratio 0.78 and overlap 0.72, and every score
gate passed it. Two checks guard against that:

* :func:`find_ambiguity`: the inlier score of the aligned clouds is profiled along the street
  (the reference structure's main horizontal axis) and along the weakest direction of the ICP
  Hessian, on a grid of half the overlap voxel out to the structure's radius. Each of the best
  separate peaks of that profile seeds a re-registration; the candidate is ambiguous when one of
  them converges to a different solution that scores at least ``ambiguity_score_ratio`` of the
  chosen one (a better-scoring one means ICP chose the wrong minimum).
* :func:`graph_gate`: the squared Mahalanobis distance between the registered
  relative pose and the one the pose graph implies, under the graph's marginal covariance of that
  relative pose plus the registration's own; a correction far outside the odometry's accumulated
  uncertainty is rejected.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from common.geometry import relative_motion, transform_points
from slam.algorithm.graph.gtsam_poses import mahalanobis_distance2

Aligner = Callable[[np.ndarray], np.ndarray]
"""Re-registers the query from an initial ``T_ref_query`` guess and returns the converged pose."""


@dataclass
class Ambiguity:
    """The best alternative solution found by :func:`find_ambiguity`.

    Attributes:
        T_ref_query: the alternative's converged pose.
        score: its inlier score.
        separation_m, separation_deg: how far it lies from the chosen solution.
    """

    T_ref_query: np.ndarray
    score: float
    separation_m: float
    separation_deg: float


def inlier_score(
    tree: cKDTree, query: np.ndarray, T_ref_query: np.ndarray, inlier_distance_m: float
) -> float:
    """Fraction of ``query`` points within ``inlier_distance_m`` of the reference after ``T``."""
    if len(query) == 0:
        return 0.0
    moved = transform_points(T_ref_query, query)
    distances, _ = tree.query(moved, k=1, distance_upper_bound=inlier_distance_m)  # inf beyond
    return float(np.mean(distances < inlier_distance_m))


def search_directions(reference: np.ndarray, covariance: np.ndarray | None) -> list[np.ndarray]:
    """Unit directions (reference frame) to shift along: the street's main horizontal axis, and
    the registration's least certain translation direction (the largest eigenvector of its
    covariance's translation block, the weakest direction of the Hessian) when it differs."""
    xy = reference[:, :2] - reference[:, :2].mean(axis=0)
    _, vectors = np.linalg.eigh(xy.T @ xy)
    directions = [np.array([vectors[0, 1], vectors[1, 1], 0.0])]
    if covariance is not None and np.all(np.isfinite(covariance)):
        _, vectors = np.linalg.eigh(covariance[3:, 3:])
        weakest = vectors[:, -1] / np.linalg.norm(vectors[:, -1])
        if abs(float(weakest @ directions[0])) < 0.9:
            directions.append(weakest)
    return directions


def _shifted(T: np.ndarray, direction: np.ndarray, offset_m: float) -> np.ndarray:
    shifted = T.copy()
    shifted[:3, 3] += offset_m * direction
    return shifted


def _peaks(offsets: np.ndarray, profile: np.ndarray, min_separation_m: float) -> list[int]:
    """Indices of the local maxima of ``profile`` at least ``min_separation_m`` from 0."""
    padded = np.concatenate([[-np.inf], profile, [-np.inf]])
    is_peak = (profile >= padded[:-2]) & (profile > padded[2:])
    return [int(k) for k in np.flatnonzero(is_peak & (np.abs(offsets) >= min_separation_m))]


def find_ambiguity(
    reference: np.ndarray,
    query: np.ndarray,
    T_ref_query: np.ndarray,
    covariance: np.ndarray | None,
    align: Aligner,
    *,
    inlier_distance_m: float,
    step_m: float,
    max_offset_m: float,
    min_separation_m: float,
    min_separation_deg: float,
    max_realignments: int,
    seed_ratio: float = 0.5,
    tree: cKDTree | None = None,
    profile_query: np.ndarray | None = None,
) -> tuple[float, Ambiguity | None]:
    """The chosen solution's inlier score and the best-scoring alternative solution, if any.

    ``reference`` and ``query`` are the clouds the scores count (structure above the ground);
    ``covariance`` is the registration's (``[rot, trans]``), or None.
    The score is profiled at offsets of ``step_m`` out to ``max_offset_m`` along each of
    :func:`search_directions`; the ``max_realignments`` best peaks that lie at least
    ``min_separation_m`` away and score at least ``seed_ratio`` of the unshifted pose are
    re-registered with ``align``. An alternative counts when it converges at least
    ``min_separation_m`` or ``min_separation_deg`` from ``T_ref_query``. ``tree``: a KD-tree of
    ``reference`` already built (else one is). ``profile_query``: the points the profile and its
    seed threshold count (a subsample of ``query``, for a cheaper profile), else ``query``; the
    returned scores always count all of ``query``.
    """
    if tree is None:
        tree = cKDTree(reference)
    score = inlier_score(tree, query, T_ref_query, inlier_distance_m)
    if profile_query is None:
        profile_query, profile_score = query, score
    else:
        profile_score = inlier_score(tree, profile_query, T_ref_query, inlier_distance_m)
    offsets = np.arange(-max_offset_m, max_offset_m + 1e-9, step_m)
    seeds: list[tuple[float, np.ndarray]] = []
    for direction in search_directions(reference, covariance):
        profile = np.array(
            [
                inlier_score(
                    tree, profile_query, _shifted(T_ref_query, direction, o), inlier_distance_m
                )
                for o in offsets
            ]
        )
        for k in _peaks(offsets, profile, min_separation_m):
            if profile[k] >= seed_ratio * profile_score:
                seeds.append((float(profile[k]), _shifted(T_ref_query, direction, offsets[k])))
    best: Ambiguity | None = None
    for _, guess in sorted(seeds, key=lambda s: -s[0])[:max_realignments]:
        T_alt = align(guess)
        if not np.all(np.isfinite(T_alt)):
            continue
        separation_m, separation_deg = relative_motion(T_ref_query, T_alt)
        if separation_m < min_separation_m and separation_deg < min_separation_deg:
            continue  # converged back to the chosen solution
        alt_score = inlier_score(tree, query, T_alt, inlier_distance_m)
        if best is None or alt_score > best.score:
            best = Ambiguity(T_alt, alt_score, separation_m, separation_deg)
    return score, best


def graph_gate(
    T_graph: np.ndarray,
    covariance_graph: np.ndarray,
    T_registered: np.ndarray,
    covariance_registered: np.ndarray | None,
    probability: float,
) -> tuple[float, str | None]:
    """The chi-square gate (6 dof) of a registration against the graph's estimate: its squared
    Mahalanobis distance (:func:`mahalanobis_distance2`) and the rejection reason, None when it
    lies within the ``probability`` quantile. The quantile is scipy.special's inverse survival
    function: ``scipy.stats`` costs about a second to import, on the worker mid-run."""
    from scipy.special import chdtri

    distance2 = mahalanobis_distance2(
        T_graph, covariance_graph, T_registered, covariance_registered
    )
    limit = float(chdtri(6, 1.0 - probability))
    if distance2 > limit:
        return (
            distance2,
            f"inconsistent with the graph: mahalanobis^2 {distance2:.1f} > {limit:.1f}",
        )
    return distance2, None
