"""The pipeline's main-thread view of the pose graph, which the submap worker owns.

The submap worker (:mod:`slam.algorithm.map_worker`) closes submaps, detects loops and updates
the pose graph; after each closed submap it publishes a :class:`GraphSnapshot`. The main thread
takes the snapshot of a submap's job when the *next* submap closes (or when it drains the
workers), a point fixed by the frames, not by the timing, so every :class:`FrameResult` is the
same whether the workers run on threads or inline. Anchors opened since the snapshot are
predicted the way the graph initialises them: the last known anchor composed with the odometry
motion between the two anchors.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from slam.algorithm.loops.base import LoopCandidate
from slam.algorithm.remap import RemapEvent

if TYPE_CHECKING:
    from slam.algorithm.merge.relocalise import Relocalisation


@dataclass
class GraphSnapshot:
    """What a submap job leaves for the main thread after closing a submap.

    Attributes:
        anchors: every anchor's estimate after the job's loop edges, ``{submap_id: T_W_A}``.
        candidates: the loop candidates the job examined.
        inliers: the graph's inlier decisions, by ``(i, j)``, of the loop edges added or changed
            since the previous snapshot (GNC may flip an old edge at any optimisation).
        num_accepted: loop edges added to the graph so far.
        loop_added: the job added a loop edge or relocalised the session (the anchors moved).
        remap: the remapping pass the job ran when it moved a submap (inline map worker only).
        relocalised: the session's placement in a stored map, when this job found it.
        map_anchored: the submaps anchored in a stored map by a prior the graph keeps, each with
            the stored submaps its registration was made to.
    """

    anchors: dict[int, np.ndarray]
    candidates: list[LoopCandidate]
    inliers: dict[tuple[int, int], bool]
    num_accepted: int
    loop_added: bool
    remap: RemapEvent | None = None
    relocalised: Relocalisation | None = None
    map_anchored: dict[int, tuple[int, ...]] = field(default_factory=dict)


@dataclass
class GraphView:
    """The anchors, loop candidates and counters as of the last snapshot taken."""

    anchors: dict[int, np.ndarray] = field(default_factory=dict)
    odometry_anchors: dict[int, np.ndarray] = field(default_factory=dict)
    loop_candidates: list[LoopCandidate] = field(default_factory=list)
    num_accepted: int = 0
    relocalisation: Relocalisation | None = None
    map_anchored: dict[int, tuple[int, ...]] = field(default_factory=dict)
    _last_known: int | None = None
    _accepted: dict[tuple[int, int], list[LoopCandidate]] = field(default_factory=dict)
    _new_loops: list[LoopCandidate] = field(default_factory=list)
    _loop_added: bool = False
    _remap: RemapEvent | None = None
    _relocalised: Relocalisation | None = None

    def add_anchor(self, submap_id: int, T_W_A_odometry: np.ndarray) -> None:
        """A submap opened (its anchor reaches the graph with the submap worker's next job)."""
        self.odometry_anchors[submap_id] = T_W_A_odometry

    def apply(self, snapshot: GraphSnapshot) -> None:
        """Take a submap job's snapshot (every one, in job order): O(what the job changed), not
        O(every candidate so far)."""
        self.anchors = snapshot.anchors
        self.map_anchored = snapshot.map_anchored
        if snapshot.anchors:
            self._last_known = max(snapshot.anchors)
        self.loop_candidates.extend(snapshot.candidates)
        for candidate in snapshot.candidates:
            if candidate.accepted:
                key = (candidate.reference_id, candidate.query_id)
                self._accepted.setdefault(key, []).append(candidate)
        for key, inlier in snapshot.inliers.items():
            for candidate in self._accepted.get(key, ()):
                candidate.graph_inlier = inlier
        self.num_accepted = snapshot.num_accepted
        self._new_loops.extend(snapshot.candidates)
        self._loop_added |= snapshot.loop_added
        self._remap = snapshot.remap if snapshot.remap is not None else self._remap
        if snapshot.relocalised is not None:
            self.relocalisation = self._relocalised = snapshot.relocalised

    def take_news(
        self,
    ) -> tuple[list[LoopCandidate], RemapEvent | None, bool, Relocalisation | None]:
        """Loop candidates, remap, whether the anchors moved (a loop was added or the session
        relocalised) and the relocalisation, each since the last call."""
        news = (self._new_loops, self._remap, self._loop_added, self._relocalised)
        self._new_loops, self._remap, self._loop_added, self._relocalised = [], None, False, None
        return news

    def pose(self, submap_id: int) -> np.ndarray:
        """The anchor's estimate: the snapshot's, or predicted from the last known anchor."""
        known = self.anchors.get(submap_id)
        if known is not None:
            return known
        T_W_A = self.odometry_anchors[submap_id]
        if self._last_known is None:  # the first anchor is the odometry's pose
            return T_W_A
        last = self._last_known
        return self.anchors[last] @ np.linalg.inv(self.odometry_anchors[last]) @ T_W_A

    def poses(self) -> dict[int, np.ndarray]:
        """Every opened anchor's estimate (see :meth:`pose`)."""
        return {i: self.pose(i) for i in self.odometry_anchors}
