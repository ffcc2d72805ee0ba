"""What every loop detector reports, and the interface the pipeline calls."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from slam.algorithm.loops.place import PlaceDescriptor
from slam.algorithm.submaps import SubmapRecord

if TYPE_CHECKING:
    pass

RelativeCovariance = Callable[[int, int], np.ndarray]
"""``(i, j) ->`` the pose graph's 6x6 covariance of ``T_Ai_Aj``
(:meth:`slam.algorithm.graph.pose_graph.PoseGraph.relative_covariance`)."""


@dataclass
class LoopCandidate:
    """One loop hypothesis between an older submap ``reference_id`` (i) and ``query_id`` (j).

    Attributes:
        accepted: passed geometric verification (the pose graph may still reject it).
        reason: ``accepted`` or why it was rejected, e.g. ``overlap 0.12 < 0.30``.
        T_Ai_Aj: the verified relative pose (or the last estimate before rejection), or None.
        scores: diagnostics of detection and verification (inliers, overlap, residuals...).
        detector: what proposed it (``map_closures``, ``proximity``, ``orb``).
        graph_inlier: set by the pipeline after the pose graph solved with this edge.
        covariance: 6x6 covariance of ``T_Ai_Aj`` from the registration (GTSAM's tangent order
            ``[rx, ry, rz, tx, ty, tz]``, right perturbation), or None for the graph's default.
    """

    reference_id: int
    query_id: int
    accepted: bool
    reason: str
    T_Ai_Aj: np.ndarray | None = None
    scores: dict[str, float] = field(default_factory=dict)
    detector: str = ""
    graph_inlier: bool | None = None
    covariance: np.ndarray | None = None


class Verification(NamedTuple):
    """What a loop verifier concludes about one pair: ``(accepted, reason, T_ref_query, scores,
    covariance)``.

    Attributes:
        accepted: passed every check.
        reason: ``accepted`` or why it was rejected.
        T_ref_query: the registered relative pose (or the last estimate before rejection), or
            None when no stage produced one.
        scores: diagnostics of the checks.
        covariance: 6x6 covariance of ``T_ref_query`` from the registration (``[rot, trans]``)
            when accepted and the registration gives one, else None.
    """

    accepted: bool
    reason: str
    T_ref_query: np.ndarray | None
    scores: dict[str, float]
    covariance: np.ndarray | None = None

    def candidate(self, reference_id: int, query_id: int, detector: str) -> LoopCandidate:
        """The loop candidate between two submaps whose anchors this pair is."""
        return LoopCandidate(
            reference_id,
            query_id,
            self.accepted,
            self.reason,
            self.T_ref_query,
            self.scores,
            detector,
            covariance=self.covariance if self.accepted else None,
        )


class LoopDetector(ABC):
    """Finds and verifies loops of a newly closed submap against the older ones.

    Attributes:
        descriptors: the place descriptor of every submap processed, ``{submap_id: descriptor}``
            (kept in the run's session for a later merge, and matched by a relocalisation).
    """

    def __init__(self) -> None:
        self.descriptors: dict[int, PlaceDescriptor] = {}

    @abstractmethod
    def process(
        self,
        submap: SubmapRecord,
        T_W_A_estimates: dict[int, np.ndarray],
        relative_covariance: RelativeCovariance | None = None,
    ) -> list[LoopCandidate]:
        """Add ``submap`` to the database and return its verified and rejected candidates.

        ``T_W_A_estimates`` holds the current estimate of every anchor in the pose graph;
        ``relative_covariance`` gives the graph's uncertainty of the relative pose of two
        anchors, for detectors that check an edge against it (None: no such check).
        """

    def release(self) -> None:
        """Drop what only the verification of later submaps needs (after the last submap: the
        pipeline's :meth:`~slam.algorithm.pipeline.SlamPipeline.finish`); the place descriptors
        stay for the session. Nothing by default."""
        return
