"""The submap worker's side of a run in a stored map (``slam.run --map``).

Until the session is placed, each closed submap is tried against the stored map by its place
descriptor (:class:`~slam.algorithm.merge.relocalise.Relocaliser`); the first that verifies moves
the pose graph into the map's frame. From then on (``LocaliseConfig.continuous``) every closed
submap is registered to the stored map near its estimate
(:mod:`slam.algorithm.merge.map_constraints`) and each verified registration becomes a prior on
its anchor in the map's frame (the placing submap's own registration included). A submap whose
anchor holds such a prior that the graph keeps is *map-anchored*; the others are odometry-only.
A stretch the map does not cover is logged once, when the run leaves the map, and once more when
it re-enters it.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

from slam.algorithm.graph.pose_graph import PoseGraph
from slam.algorithm.submaps import SubmapRecord

if TYPE_CHECKING:
    from slam.algorithm.loops.place import PlaceDescriptor
    from slam.algorithm.merge.map_constraints import MapConstraint
    from slam.algorithm.merge.relocalise import Relocalisation, Relocaliser

logger = logging.getLogger(__name__)

NOT_COVERED = "no stored submap near it"
"""``MapConstraint.reason`` of a submap in a place the stored map does not cover."""


def _frames(record: SubmapRecord) -> tuple[int, int]:
    return int(record.frame_indices[0]), int(record.frame_indices[-1])


class MapLocalisation:
    """Placement and map constraints of a live session (module docstring); the submap worker's."""

    def __init__(self, relocaliser: Relocaliser) -> None:
        self.relocaliser = relocaliser
        self.placement: Relocalisation | None = None
        self.constraints: list[MapConstraint] = []
        self._in_map = True  # the last submap was map-anchored (a gap is logged once)
        self.registration_seconds = 0.0  # registering submaps after the placement

    @property
    def continuous(self) -> bool:
        return self.relocaliser.localise.continuous

    @property
    def holds_attitude(self) -> bool:
        """The map's priors hold the run's attitude: placed, continuous, and the last closed
        submap map-anchored (a new anchor then needs no gravity measurement, unless
        ``gravity_while_anchored``)."""
        cfg = self.relocaliser.localise
        placed = self.placement is not None and self.continuous
        return placed and self._in_map and not cfg.gravity_while_anchored

    def on_submap_closed(
        self, record: SubmapRecord, graph: PoseGraph, descriptor: PlaceDescriptor | None
    ) -> tuple[Relocalisation | None, bool]:
        """Place the session or constrain a closed submap; returns the placement when this
        submap made it, and whether the graph's estimate moved."""
        from slam.algorithm.merge.map_constraints import MapConstraint

        submap_id = record.submap_id
        if self.placement is None:
            found = self.relocaliser.locate(
                submap_id, _frames(record), descriptor, record.points_A, graph.pose(submap_id)
            )
            if found is None:
                return None, False
            cfg = self.relocaliser.localise
            loose = (cfg.placement_prior_sigma_rad, cfg.placement_prior_sigma_m)
            graph.reframe(found.T_M_W, loose if self.continuous else None)
            self.placement = found
            if self.continuous:
                T_M_A = graph.pose(submap_id)
                edge = graph.add_map_prior(submap_id, T_M_A, found.covariance)
                ids = [found.map_submap_id]
                placed = MapConstraint(submap_id, ids, edge.inlier, "placement", T_M_A)
                placed.covariance, placed.scores = found.covariance, dict(found.scores)
                self.constraints.append(placed)
            return found, True
        if not self.continuous:
            return None, False
        T_M_A = graph.pose(submap_id)
        start = time.perf_counter()
        constraint = self.relocaliser.constraints.register(
            submap_id, record.points_A, T_M_A, graph.anchor_covariance
        )
        self.registration_seconds += time.perf_counter() - start
        if constraint is None:
            constraint = MapConstraint(submap_id, [], False, NOT_COVERED, T_M_A)
        moved = False
        if constraint.accepted:
            edge = graph.add_map_prior(submap_id, constraint.T_M_A, constraint.covariance)
            constraint.accepted = edge.inlier
            if not edge.inlier:
                constraint.reason = "rejected by the pose graph (GNC)"
            moved = True
        self.constraints.append(constraint)
        self._log_coverage(record, constraint)
        return None, moved

    def _log_coverage(self, record: SubmapRecord, constraint: MapConstraint) -> None:
        first, last = _frames(record)
        if self._in_map and not constraint.accepted:
            logger.warning(
                "left the map at frames %d-%d (submap %d: %s); odometry only until the run "
                "re-enters it",
                first,
                last,
                record.submap_id,
                constraint.reason,
            )
        elif not self._in_map and constraint.accepted:
            logger.info(
                "back in the map at frames %d-%d (submap %d on the map's submaps %s)",
                first,
                last,
                record.submap_id,
                constraint.map_submap_ids,
            )
        self._in_map = constraint.accepted

    def anchored(self, graph: PoseGraph) -> dict[int, tuple[int, ...]]:
        """Live submaps whose anchor holds a map prior the graph keeps (without
        ``continuous``: the placing submap, which the placement alone ties to the map), each
        with the stored submaps its registration was made to (nearest first)."""
        if self.placement is None:
            return {}
        if not self.continuous:
            return {self.placement.submap_id: (self.placement.map_submap_id,)}
        kept = {edge.j for edge in graph.map_priors if edge.inlier}
        return {
            c.submap_id: tuple(c.map_submap_ids) for c in self.constraints if c.submap_id in kept
        }
