"""Continuous localisation: every closed live submap registered to the stored map near it.

After the first placement (:mod:`slam.algorithm.merge.relocalise`) the live pose graph is in the
map's frame. Each later submap the live run closes is registered to the stored map where its
current estimate says it is: the stored submaps whose surface centres (their voxels, in the map's
frame) lie near the live submap's centre are the candidates, not the place descriptors, so a
submap is registered even where the descriptors would find nothing. The decoded surfaces of the
``max_map_submaps`` nearest (their own latents, as the merge decodes them) are put together in the
map's frame, and the live submap's points are aligned to them by the merge's point-to-plane ICP
and gates (:func:`slam.algorithm.merge.surface.verify`) from the current estimate ``T_M_A``, with
a stricter overlap (``LocaliseConfig.min_inlier_fraction``: a submap that sees the stored surface
only in part is pulled by the rest) and a covariance that carries the surfaces' systematic error
(:func:`registration_covariance`). A registration that passes is checked like a LiDAR loop: for
ambiguity along the street (:func:`slam.algorithm.loops.ambiguity.find_ambiguity`) and against
the graph (:func:`slam.algorithm.graph.gtsam_poses.mahalanobis_distance2` of the registered anchor
pose from the graph's, under the graph's marginal covariance of the anchor plus the
registration's). The result is a prior on the anchor in the map's frame (the stored map is fixed:
the live session never bends it), which the pose graph judges by GNC like a loop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from common.geometry import transform_points
from common.point_to_plane import IcpResult
from common.voxel_keys import unpack_keys
from mapping.neural_map import Submap
from slam.algorithm.loops.ambiguity import find_ambiguity, graph_gate
from slam.algorithm.merge.config import LocaliseConfig, MergeConfig
from slam.algorithm.merge.surface import SurfaceDecoder, align_surfaces, icp_covariance, verify

AnchorCovariance = Callable[[int], np.ndarray]
"""The graph's 6x6 marginal covariance of an anchor (``[rot, trans]``) in the map's frame."""


@dataclass
class MapConstraint:
    """One live submap's registration to the stored map.

    Attributes:
        submap_id: the live submap.
        map_submap_ids: the stored submaps whose surfaces were the reference (nearest first).
        accepted: every gate passed (the graph then judges it by GNC).
        reason: ``accepted`` or why not.
        T_M_A: the registered anchor pose in the map's frame (the estimate when none).
        covariance: 6x6 covariance of ``T_M_A`` (``[rot, trans]``), when accepted.
        scores: the verification's scores.
    """

    submap_id: int
    map_submap_ids: list[int]
    accepted: bool
    reason: str
    T_M_A: np.ndarray
    covariance: np.ndarray | None = None
    scores: dict[str, float] = field(default_factory=dict)


def subsample(points: np.ndarray, count: int) -> np.ndarray:
    """At most ``count`` of ``points``, a fixed random subset in their order."""
    if len(points) <= count:
        return points
    return points[np.sort(np.random.default_rng(0).choice(len(points), count, replace=False))]


def _centre_radius(points: np.ndarray) -> tuple[np.ndarray, float]:
    centre = points.mean(axis=0)
    return centre, float(np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1))))


def registration_covariance(
    result: IcpResult, scores: dict[str, float], query: np.ndarray, merge: MergeConfig
) -> np.ndarray:
    """6x6 covariance (``[rot, trans]``) of a registration to the stored map.

    The ICP's (:func:`~slam.algorithm.merge.surface.icp_covariance`) treats the thousands of
    point residuals as independent, so it claims about a millimetre, floored at the merge's
    1 cm / 0.1 deg. A decoded surface and a live submap differ systematically by about their
    residual spread, over the whole overlap at once: measured on 7-Scenes redkitchen, accepted
    registrations were 1 to 8 cm off the truth and turned by a degree or more, so the first
    ones' tight rotation made the graph reject a later correct one (and GNC the placement's).
    The floor added here is that systematic error: translation sigma the robust residual
    sigma over the inlier fraction (a surface seen in part pins the pose less), rotation sigma
    that over the query's RMS radius (an offset of that size at its extent)."""
    sigma_m = scores["residual_sigma_m"] / max(scores["inlier_fraction"], 1e-3)
    radius_m = max(_centre_radius(query)[1], 1e-3)
    floor = np.array([sigma_m / radius_m] * 3 + [sigma_m] * 3) ** 2
    return icp_covariance(result, merge) + np.diag(floor)


class MapConstraints:
    """Registers closed live submaps to the stored map near their estimates (module docstring)."""

    def __init__(
        self,
        submaps: dict[int, Submap],
        T_M_A: dict[int, np.ndarray],
        decoder: SurfaceDecoder,
        voxel_size_m: float,
        merge: MergeConfig,
        cfg: LocaliseConfig,
    ) -> None:
        self.cfg = cfg
        self._merge = merge
        self._V = voxel_size_m
        self._decoder = decoder
        self._submaps = {i: s for i, s in submaps.items() if i in T_M_A}
        self._T_M_A = T_M_A
        ids, centres, radii = [], [], []
        for i, submap in self._submaps.items():
            keys = submap.original.keys.cpu().numpy()
            if len(keys) == 0:
                continue
            centres_W = (unpack_keys(keys) + 0.5) * voxel_size_m
            T_M_W = T_M_A[i] @ np.linalg.inv(submap.T_W_A_encoded)
            centre, radius = _centre_radius(transform_points(T_M_W, centres_W))
            ids.append(i)
            centres.append(centre)
            radii.append(radius)
        self._ids = np.array(ids, dtype=np.int64)
        self._centres = np.array(centres).reshape(-1, 3)
        self._radii = np.array(radii)

    def decode_all(self, threads: int = 1) -> None:
        """Decode every stored submap's surface now on ``threads`` threads (before the first
        frame of a localisation run, so that no frame waits for it)."""
        self._decoder.decode_many(
            [(("map", i), self._submaps[i]) for i in self._ids.tolist()], threads
        )

    def near(self, points_A: np.ndarray, T_M_A: np.ndarray) -> list[int]:
        """The stored submaps near a live submap (its points in its anchor frame, its estimate
        ``T_M_A``), nearest first, at most ``max_map_submaps``."""
        if len(self._ids) == 0 or len(points_A) == 0:
            return []
        centre_A, radius = _centre_radius(points_A)
        centre = transform_points(T_M_A, centre_A[None])[0]
        distance = np.linalg.norm(self._centres - centre, axis=1)
        near = distance <= self.cfg.near_factor * (self._radii + radius)
        order = np.argsort(distance)
        return [int(self._ids[k]) for k in order if near[k]][: self.cfg.max_map_submaps]

    def _reference(self, ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """The decoded surfaces of the stored submaps ``ids`` in the map's frame."""
        points, normals = [], []
        for i in ids:
            p_A, n_A = self._decoder(("map", i), self._submaps[i])
            T = self._T_M_A[i]
            points.append(transform_points(T, p_A))
            normals.append(n_A @ T[:3, :3].T)
        return np.concatenate(points), np.concatenate(normals)

    def register(
        self,
        submap_id: int,
        points_A: np.ndarray,
        T_M_A: np.ndarray,
        anchor_covariance: AnchorCovariance | None = None,
    ) -> MapConstraint | None:
        """Register one closed live submap from its estimate ``T_M_A``; None when no stored
        submap is near it (a place the map does not cover)."""
        ids = self.near(points_A, T_M_A)
        if not ids:
            return None
        merge = self._merge
        query = np.asarray(subsample(points_A, self.cfg.max_query_points), dtype=np.float64)
        coarse = self._coarse(query)
        reference = self._reference(ids)
        tree = cKDTree(reference[0])
        accepted, reason, T, scores, result = verify(
            reference, (query, np.zeros((0, 3))), T_M_A, self._V, merge, tree, coarse
        )
        if accepted and scores["inlier_fraction"] < self.cfg.min_inlier_fraction:
            accepted = False
            reason = (
                f"partial overlap: inlier fraction {scores['inlier_fraction']:.2f} < "
                f"{self.cfg.min_inlier_fraction:.2f}"
            )
        constraint = MapConstraint(submap_id, ids, accepted, reason, T, scores=scores)
        if not accepted:
            constraint.T_M_A = T_M_A
            return constraint
        constraint.covariance = registration_covariance(result, scores, query, merge)
        graph = None if anchor_covariance is None else anchor_covariance(submap_id)
        if graph is None or self._graph_may_be_fooled(graph):
            self._check_ambiguity(constraint, reference, query, coarse, tree)
        if constraint.accepted and graph is not None:
            self._check_graph(constraint, T_M_A, graph)
        return constraint

    def _coarse(self, query: np.ndarray) -> np.ndarray | None:
        """The query points of the registration's gates wider than half a voxel
        (:func:`~slam.algorithm.merge.surface.align_surfaces`), or None: all of them."""
        count = self.cfg.coarse_query_points
        return None if count == 0 or count >= len(query) else subsample(query, count)

    def _graph_may_be_fooled(self, covariance: np.ndarray) -> bool:
        """Whether an alternative solution ``ambiguity_min_separation_vu`` away could pass the
        graph's chi-square gate: the graph's 3-sigma position uncertainty of the anchor reaches
        that far (after a long stretch without the map). Otherwise that gate rejects every such
        alternative, and the costly ambiguity search is skipped."""
        sigma_m = float(np.sqrt(max(np.linalg.eigvalsh(covariance[3:, 3:]).max(), 0.0)))
        reach_m = self.cfg.ambiguity_min_separation_vu * self._V
        return self.cfg.graph_consistency_probability <= 0 or 3.0 * sigma_m >= reach_m

    def _check_ambiguity(
        self,
        constraint: MapConstraint,
        reference: tuple[np.ndarray, np.ndarray],
        query: np.ndarray,
        coarse: np.ndarray | None,
        tree: cKDTree,
    ) -> None:
        c, V = self.cfg, self._V
        if not c.ambiguity_check:
            return

        def realign(guess: np.ndarray) -> np.ndarray:
            return align_surfaces(reference, query, guess, V, self._merge, tree, coarse).T_ref_query

        radius = _centre_radius(reference[0])[1]
        score, alternative = find_ambiguity(
            reference[0],
            query,
            constraint.T_M_A,
            constraint.covariance,
            realign,
            inlier_distance_m=self._merge.overlap_gate_vu * V,
            step_m=c.ambiguity_step_vu * V,
            max_offset_m=min(c.ambiguity_max_offset_vu * V, radius),
            min_separation_m=c.ambiguity_min_separation_vu * V,
            min_separation_deg=c.ambiguity_min_separation_deg,
            max_realignments=c.ambiguity_max_realignments,
            tree=tree,
            profile_query=coarse,
        )
        constraint.scores["ambiguity_score"] = score
        if alternative is not None and alternative.score >= c.ambiguity_score_ratio * score:
            constraint.accepted = False
            constraint.reason = (
                f"ambiguous: a solution {alternative.separation_m:.2f} m / "
                f"{alternative.separation_deg:.1f} deg away scores {alternative.score:.2f} "
                f"(chosen {score:.2f})"
            )

    def _check_graph(
        self, constraint: MapConstraint, T_M_A_graph: np.ndarray, covariance: np.ndarray
    ) -> None:
        probability = self.cfg.graph_consistency_probability
        if probability <= 0:
            return
        distance2, reason = graph_gate(
            T_M_A_graph, covariance, constraint.T_M_A, constraint.covariance, probability
        )
        constraint.scores["graph_mahalanobis2"] = distance2
        if reason is not None:
            constraint.accepted = False
            constraint.reason = reason
