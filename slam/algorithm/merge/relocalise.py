"""Relocalisation of a live session in a stored map (``slam.run ... --map``).

Every submap the live run closes, until one is placed, is matched against the stored map's
submaps by place descriptor (:func:`slam.algorithm.merge.merge.rank_matches`, the merge's candidate
search) and verified by the merge's point-to-plane ICP and gates
(:func:`slam.algorithm.merge.surface.verify`). The stored side of the registration is the surface
decoded from the stored submap's own latents (the stored run's scans are gone); the live side is the
submap's own points. The first verified match gives ``T_M_W``, the live world frame in the map's
frame. The pipeline then re-expresses its pose graph in the map's frame
(:meth:`slam.algorithm.graph.pose_graph.PoseGraph.reframe`) and remaps the submaps it has
encoded, so every later pose and submap is in the map's frame.

A run that starts outside the stored map is tried again at each submap it closes: it joins the
map when it enters it. After that, with ``LocaliseConfig.continuous``, every closed submap is
registered to the stored map near its estimate (:mod:`slam.algorithm.merge.map_constraints`) and
becomes a prior on its anchor in the map's frame.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from common.geometry import orthonormalize
from mapping.neural_map import NeuralMap
from slam.algorithm.loops.place import PlaceDescriptor
from slam.algorithm.merge.config import LocaliseConfig, MergeConfig
from slam.algorithm.merge.map_constraints import (
    MapConstraints,
    registration_covariance,
    subsample,
)
from slam.algorithm.merge.merge import SessionInput, rank_matches
from slam.algorithm.merge.surface import SurfaceDecoder, verify

logger = logging.getLogger(__name__)


@dataclass
class Relocalisation:
    """Where a live session was placed in the stored map.

    Attributes:
        submap_id: the live submap whose registration placed the session.
        frames: first and last frame index of that submap.
        map_submap_id: the stored submap it registered to (its id in the map's session).
        T_M_W: the live session's world frame in the map's frame.
        T_Am_A: the live submap's anchor seen from the stored submap's anchor.
        attempts: live submaps tried, this one included.
        scores: the verification's scores (inlier fraction, residual, correction, ...).
        covariance: 6x6 covariance (``[rot, trans]``) of the registration, hence of the placed
            anchor's pose in the map's frame.
    """

    submap_id: int
    frames: tuple[int, int]
    map_submap_id: int
    T_M_W: np.ndarray
    T_Am_A: np.ndarray
    attempts: int
    scores: dict[str, float] = field(default_factory=dict)
    covariance: np.ndarray | None = None


class Relocaliser:
    """Places the submaps of a live session in a stored map (see the module docstring)."""

    def __init__(
        self,
        stored: SessionInput,
        stored_map: NeuralMap,
        cfg: MergeConfig | None = None,
        localise: LocaliseConfig | None = None,
    ) -> None:
        self.cfg = cfg or MergeConfig()
        self.localise = localise or LocaliseConfig()
        self._voxel_size_m = stored_map.voxel_size_m
        self._decoder = SurfaceDecoder(
            stored_map, self.cfg.surface_max_points, self.cfg.surface_subdivisions
        )
        self._submaps = {s.submap_id: s for s in stored.submaps}
        self._T_M_A = stored.session.anchor_poses()
        self._references = [
            (i, descriptor)
            for i, descriptor in stored.session.descriptors.items()
            if i in self._submaps and i in self._T_M_A
        ]
        self.constraints = MapConstraints(  # the registrations after the placement
            self._submaps,
            self._T_M_A,
            self._decoder,
            self._voxel_size_m,
            self.cfg,
            self.localise,
        )
        self.attempts = 0
        self.seconds = 0.0
        self.decode_seconds = 0.0  # decoding every stored surface ahead (decode_map)

    @property
    def map_anchor_poses(self) -> dict[int, np.ndarray]:
        """Every stored submap's anchor pose in the map's frame, ``{submap_id: T_M_A}``."""
        return self._T_M_A

    def decode_map(self, threads: int = 1) -> float:
        """Decode every stored submap's surface ahead (a localisation run) on ``threads``
        threads; returns seconds."""
        start = time.perf_counter()
        self.constraints.decode_all(threads)
        self.decode_seconds = time.perf_counter() - start
        return self.decode_seconds

    def locate(
        self,
        submap_id: int,
        frames: tuple[int, int],
        descriptor: PlaceDescriptor | None,
        points_A: np.ndarray,
        T_W_A: np.ndarray,
    ) -> Relocalisation | None:
        """Try to place one closed live submap (its frame range, descriptor, points in its
        anchor frame and anchor estimate ``T_W_A``); None when no stored submap verifies."""
        if descriptor is None or len(points_A) == 0:
            return None
        start = time.perf_counter()
        self.attempts += 1
        try:
            return self._locate(submap_id, frames, descriptor, points_A, T_W_A)
        finally:
            self.seconds += time.perf_counter() - start

    def _locate(
        self,
        submap_id: int,
        frames: tuple[int, int],
        descriptor: PlaceDescriptor,
        points_A: np.ndarray,
        T_W_A: np.ndarray,
    ) -> Relocalisation | None:
        cfg = self.cfg
        points_A = subsample(points_A, cfg.surface_max_points)
        query = (np.asarray(points_A, dtype=np.float64), np.zeros((0, 3)))
        matches = rank_matches(descriptor, self._references, self._voxel_size_m, cfg)
        for _, map_id, guess in matches:
            reference = self._decoder(("map", map_id), self._submaps[map_id])
            accepted, reason, T_Am_A, scores, result = verify(
                reference, query, guess, self._voxel_size_m, cfg
            )
            logger.info(
                "relocalisation of submap %d at map submap %d: %s", submap_id, map_id, reason
            )
            if accepted:
                T_M_W = orthonormalize(self._T_M_A[map_id] @ T_Am_A @ np.linalg.inv(T_W_A))
                return Relocalisation(
                    submap_id,
                    frames,
                    map_id,
                    T_M_W,
                    T_Am_A,
                    self.attempts,
                    scores,
                    registration_covariance(result, scores, query[0], cfg),
                )
        return None
