"""LiDAR loop closure: map_closures candidates on submap clouds, verified by ICP and overlap.

Candidates come from two places:

* map_closures (Gupta et al., ICRA 2024) turns each submap cloud into a ground-aligned bird's-eye
  density image, matches ORB features against every earlier submap and aligns the matches by 2D
  RANSAC. Its ``pose`` maps the reference submap into the query submap (``T_Aj_Ai``). It does not
  depend on the drift, but needs distinctive structure in the density image.
* pose proximity: older anchors whose current estimate lies within ``proximity_radius_m`` of the
  query anchor, with the estimated relative pose as the initial guess. This finds revisits that
  map_closures misses while the drift is small compared to the radius.

Each candidate is verified by :class:`~slam.algorithm.loops.lidar_verify.IcpVerifier` (ICP,
inliers, overlap, a constrained cost, ambiguity), then checked against the pose graph (a
Mahalanobis gate on the graph's accumulated uncertainty between the two anchors).
"""

from __future__ import annotations

import logging
from functools import partial

import numpy as np

from slam.algorithm.loops.ambiguity import graph_gate
from slam.algorithm.loops.base import LoopCandidate, LoopDetector, RelativeCovariance, Verification
from slam.algorithm.loops.config import LoopClosureConfig
from slam.algorithm.loops.lidar_verify import IcpVerifier
from slam.algorithm.loops.place import bev_descriptor
from slam.algorithm.submaps import SubmapRecord

logger = logging.getLogger(__name__)


class LidarLoopDetector(LoopDetector):
    """map_closures on the coarse submap clouds, each candidate verified by :class:`IcpVerifier`."""

    def __init__(self, cfg: LoopClosureConfig) -> None:
        from map_closures.config import MapClosuresConfig
        from map_closures.map_closures import MapClosures

        super().__init__()
        self.cfg = cfg
        lidar = cfg.lidar
        self._closures = MapClosures(
            MapClosuresConfig(
                density_map_resolution=lidar.density_map_resolution_m,
                density_threshold=lidar.density_threshold,
                hamming_distance_threshold=lidar.hamming_distance_threshold,
                inliers_threshold=lidar.inliers_threshold,
            )
        )
        self._verifier = IcpVerifier(lidar)
        self._clouds: dict[int, np.ndarray] = {}
        self._travelled: dict[int, float] = {}

    def _eligible(self, i: int, submap: SubmapRecord) -> bool:
        return (
            i in self._clouds
            and submap.submap_id - i >= self.cfg.min_submap_separation
            and submap.travelled_m - self._travelled[i] >= self.cfg.min_travel_m
        )

    def _guesses(
        self, submap: SubmapRecord, cloud: np.ndarray, T_W_A: dict[int, np.ndarray]
    ) -> dict[int, tuple[str, np.ndarray, dict[str, float]]]:
        """Candidate reference ids with their detector, ``T_Ai_Aj`` guess and scores."""
        lidar = self.cfg.lidar
        j = submap.submap_id
        guesses: dict[int, tuple[str, np.ndarray, dict[str, float]]] = {}
        for closure in self._closures.get_top_k_closures(j, cloud, lidar.top_k):
            i = int(closure.source_id)
            inliers = int(closure.number_of_inliers)
            if inliers < lidar.inliers_threshold or not self._eligible(i, submap):
                continue
            T_Aj_Ai = np.asarray(closure.pose, dtype=np.float64)
            guesses[i] = ("map_closures", np.linalg.inv(T_Aj_Ai), {"map_closures_inliers": inliers})
        if lidar.proximity_radius_m > 0 and j in T_W_A:
            near = []
            for i in self._clouds:
                if i in guesses or i not in T_W_A or not self._eligible(i, submap):
                    continue
                distance = float(np.linalg.norm(T_W_A[i][:3, 3] - T_W_A[j][:3, 3]))
                if distance <= lidar.proximity_radius_m:
                    near.append((distance, i))
            for distance, i in sorted(near)[: lidar.max_proximity_candidates]:
                guess = np.linalg.inv(T_W_A[i]) @ T_W_A[j]
                guesses[i] = ("proximity", guess, {"anchor_distance_m": distance})
        return guesses

    def _check_graph(
        self,
        i: int,
        j: int,
        verification: Verification,
        *,
        T_W_A: dict[int, np.ndarray],
        covariance: RelativeCovariance | None,
    ) -> Verification:
        """Reject an accepted edge far outside the graph's uncertainty of ``T_Ai_Aj`` (a chi-square
        gate, ``graph_consistency_probability``)."""
        probability = self.cfg.lidar.graph_consistency_probability
        if (
            not verification.accepted
            or probability <= 0
            or covariance is None
            or i not in T_W_A
            or j not in T_W_A
        ):
            return verification
        T_graph = np.linalg.inv(T_W_A[i]) @ T_W_A[j]
        distance2, reason = graph_gate(
            T_graph,
            covariance(i, j),
            verification.T_ref_query,
            verification.covariance,
            probability,
        )
        scores = dict(verification.scores, graph_mahalanobis2=distance2)
        if reason is not None:
            return Verification(False, reason, verification.T_ref_query, scores)
        return verification._replace(scores=scores)

    def process(
        self,
        submap: SubmapRecord,
        T_W_A_estimates: dict[int, np.ndarray],
        relative_covariance: RelativeCovariance | None = None,
    ) -> list[LoopCandidate]:
        cloud = np.asarray(submap.loop_points_A, dtype=np.float64)
        j = submap.submap_id
        self.descriptors[j] = bev_descriptor(cloud, self.cfg.lidar.density_map_resolution_m)
        if len(cloud) < 100:  # nothing to match (and map_closures needs a cloud)
            self._clouds[j] = submap.loop_points_A
            self._travelled[j] = submap.travelled_m
            return []
        guesses = self._guesses(submap, cloud, T_W_A_estimates)
        self._clouds[j] = submap.loop_points_A
        self._travelled[j] = submap.travelled_m
        candidates = []
        for i, (detector, guess, detection_scores) in guesses.items():
            reference = np.asarray(self._clouds[i], dtype=np.float64)
            verification = self._verifier.verify(
                reference,
                cloud,
                guess,
                limit_correction=detector != "proximity",
                graph_check=partial(
                    self._check_graph, i, j, T_W_A=T_W_A_estimates, covariance=relative_covariance
                ),
            )
            verification.scores.update(detection_scores)
            logger.debug(
                "loop %d-%d (%s): %s %s", i, j, detector, verification.reason, verification.scores
            )
            candidates.append(verification.candidate(i, j, detector))
        return candidates
