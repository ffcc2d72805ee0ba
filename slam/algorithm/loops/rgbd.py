"""RGB-D loop closure between submap keyframes: the candidates.

Candidates: older keyframes whose estimated anchor lies within ``candidate_radius_m`` of the
query anchor, ranked by the number of ORB matches that pass Lowe's ratio test, and (with
``proximity_candidates``) the nearest older anchors that ORB did not close. Each candidate is
verified by :class:`~slam.algorithm.loops.rgbd_verify.RgbdVerifier`.
"""

from __future__ import annotations

import logging

import numpy as np

from common.geometry import relative_motion
from slam.algorithm.loops.base import LoopCandidate, LoopDetector
from slam.algorithm.loops.config import LoopClosureConfig
from slam.algorithm.loops.keyframes import KeyframeFeatures
from slam.algorithm.loops.place import keyframe_descriptor
from slam.algorithm.loops.rgbd_verify import RgbdVerifier
from slam.algorithm.submaps import SubmapRecord

logger = logging.getLogger(__name__)


class RgbdLoopDetector(LoopDetector):
    """Pose-proximity + ORB candidates between keyframes, verified by :class:`RgbdVerifier`.

    With ``proximity_candidates > 0`` and refinement on, the nearest older anchors that ORB did not
    close (within ``candidate_radius_m`` and ``proximity_max_angle_deg`` of viewing direction) are
    also tried by the dense refinement alone, starting from their current relative estimate (the
    drift between them is what the loop corrects; ICP's correction limit and the keyframe depth
    agreement reject a guess that is too far off). This finds revisits whose colour does not
    match well enough for PnP (7-Scenes: colour not registered to depth, motion blur).
    """

    def __init__(self, cfg: LoopClosureConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self._verifier = RgbdVerifier(cfg.rgbd)
        self._features: dict[int, KeyframeFeatures] = {}
        self._travelled: dict[int, float] = {}

    def process(
        self,
        submap: SubmapRecord,
        T_W_A_estimates: dict[int, np.ndarray],
        relative_covariance: object = None,  # RGB-D edges are not gated on the graph
    ) -> list[LoopCandidate]:
        if submap.keyframe is None:
            return []
        j = submap.submap_id
        query = self._verifier.features(submap.keyframe, submap.points_A, submap.normals_A)
        if query is None:
            return []
        self.descriptors[j] = keyframe_descriptor(query.pixels, query.descriptors, query.points_S)
        c = self.cfg
        T_W_Aj = T_W_A_estimates.get(j)
        ranked = []
        for i, reference in self._features.items():
            if j - i < c.min_submap_separation:
                continue
            if submap.travelled_m - self._travelled[i] < c.min_travel_m:
                continue
            T_W_Ai = T_W_A_estimates.get(i)
            if T_W_Aj is not None and T_W_Ai is not None:
                distance = float(np.linalg.norm(T_W_Aj[:3, 3] - T_W_Ai[:3, 3]))
                if distance > c.rgbd.candidate_radius_m:
                    continue
            matches = self._verifier.match(reference, query)
            if len(matches) >= c.rgbd.min_matches:
                ranked.append((len(matches), i, matches))
        ranked.sort(key=lambda item: -item[0])
        candidates = []
        for _, i, matches in ranked[: c.rgbd.max_candidates]:
            verification = self._verifier.verify(self._features[i], query, matches)
            logger.debug("loop %d-%d: %s %s", i, j, verification.reason, verification.scores)
            candidates.append(verification.candidate(i, j, "orb"))
        candidates += self._proximity(j, query, submap, T_W_A_estimates, candidates)
        self._features[j] = query
        self._travelled[j] = submap.travelled_m
        return candidates

    def release(self) -> None:
        """The kept keyframes (images, features, clouds) go: no later submap can use them."""
        self._features.clear()

    def _proximity(
        self,
        j: int,
        query: KeyframeFeatures,
        submap: SubmapRecord,
        T_W_A: dict[int, np.ndarray],
        done: list[LoopCandidate],
    ) -> list[LoopCandidate]:
        c = self.cfg
        if c.rgbd.proximity_candidates == 0 or not c.rgbd.refine or j not in T_W_A:
            return []
        # Pairs whose dense refinement already ran (accepted or not) are not tried again.
        closed = {
            cand.reference_id for cand in done if cand.accepted or "dense_rmse_m" in cand.scores
        }
        near = []
        for i in self._features:
            if i in closed or i not in T_W_A or j - i < c.min_submap_separation:
                continue
            if submap.travelled_m - self._travelled[i] < c.min_travel_m:
                continue
            guess = np.linalg.inv(T_W_A[i]) @ T_W_A[j]
            distance, angle = relative_motion(np.eye(4), guess)
            # Angle between the optical axes: views that look elsewhere do not overlap.
            axis_deg = float(np.degrees(np.arccos(np.clip(guess[2, 2], -1.0, 1.0))))
            if distance <= c.rgbd.candidate_radius_m and axis_deg <= c.rgbd.proximity_max_angle_deg:
                near.append((distance + 0.01 * angle, i, guess))
        near.sort(key=lambda item: item[0])
        candidates = []
        for _, i, guess in near[: c.rgbd.proximity_candidates]:
            verification = self._verifier.verify_dense(self._features[i], query, guess)
            logger.debug(
                "loop %d-%d (proximity): %s %s", i, j, verification.reason, verification.scores
            )
            candidates.append(verification.candidate(i, j, "proximity"))
        return candidates
