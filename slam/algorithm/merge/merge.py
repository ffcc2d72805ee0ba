"""Merge sessions (separate runs) into one loop-closed neural map without their raw data.

1. Every anchor of every session gets a global id (sessions in the order given).
2. Inter-session loop candidates: each submap of a later session is matched against the submaps
   of every earlier session by the stored place descriptors: ratio-test matches with every
   earlier submap (a brute-force Hamming match, cheap), a RANSAC fit only for the few with the
   most matches (:func:`slam.algorithm.loops.place.fit_matches`); the fitted ones are verified best
   first, and the first that passes is the submap's edge. A session given twice is refused
   before this (:func:`slam.algorithm.merge.inputs.check_distinct`).
3. Verification and the relative pose come from surface points *decoded from each submap's own
   neural map* (its original encoding, meshed alone: vertices and normals of the SDF's zero
   crossing), never from scans: point-to-plane ICP from the descriptor's guess, accepted only with
   enough inliers, a small residual, a small correction of the guess and a well-conditioned cost.
4. Each later session is placed in the first session's frame by its best verified edge to a
   session already placed; a session that shares no verified place with the others is a
   :class:`MergeError` (nothing is forced).
5. One GTSAM graph over all sessions: the first session's first anchor fixed at its pose, every
   stored odometry and loop factor with its covariance, the inter-session edges; solved by GNC
   (truncated least squares; stored factors known inliers), the robust back-end of a run.
6. Every submap is re-placed at its merged anchor pose from its *original* encoding by the
   Jacobian-corrected SE(3) transform and fused into one global map.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from common.geometry import orthonormalize, relative_motion
from mapping.neural_map import NeuralMap, Submap
from slam.algorithm.graph.gravity_factors import GRAVITY_KEY, gravity_factor, gravity_frame_prior
from slam.algorithm.graph.gtsam_poses import pose3
from slam.algorithm.loops.place import PlaceDescriptor, fit_matches, ratio_matches
from slam.algorithm.merge.config import MergeConfig
from slam.algorithm.merge.inputs import (
    MergeError,
    SessionInput,
    check_compatible,
    merged_session_id,
)
from slam.algorithm.merge.session import Edge, SessionRecord
from slam.algorithm.merge.surface import SurfaceDecoder, icp_covariance, verify

__all__ = ["MergeError", "SessionInput", "merge_sessions"]

logger = logging.getLogger(__name__)


@dataclass
class InterLoop:
    """An inter-session loop candidate between global anchors ``i`` (reference) and ``j``."""

    i: int
    j: int
    session_i: int
    session_j: int
    accepted: bool
    reason: str
    T_Ai_Aj: np.ndarray | None
    scores: dict[str, float] = field(default_factory=dict)
    covariance: np.ndarray | None = None
    graph_inlier: bool | None = None


@dataclass
class MergeResult:
    """What a merge produces.

    Attributes:
        neural_map: the fused global map of every session's submaps at their merged poses.
        submaps: those submaps (global ids).
        T_W_A: merged anchor poses by global id (first session's frame).
        T_W0_Wk: each session's world frame in the first session's, from the initial alignment.
        frame_poses: per session, (N_k, 4, 4) merged frame poses.
        session: the merged run's own session record (a merged run can be merged again).
        loops: inter-session candidates, accepted or not.
        intra_loops: ``(session, global i, global j)`` of every stored loop factor.
        seconds: wall time per stage.
    """

    neural_map: NeuralMap
    submaps: list[Submap]
    T_W_A: dict[int, np.ndarray]
    T_W0_Wk: list[np.ndarray]
    frame_poses: list[np.ndarray]
    session: SessionRecord
    loops: list[InterLoop]
    intra_loops: list[tuple[int, int, int]]
    seconds: dict[str, float]


class _Ids:
    """Global anchor ids: sessions in order, anchors in graph order."""

    def __init__(self, inputs: list[SessionInput]) -> None:
        self.of: list[dict[int, int]] = []
        self.session_of: dict[int, int] = {}
        next_id = 0
        for k, item in enumerate(inputs):
            mapping = {}
            for local in item.session.node_ids.tolist():
                mapping[int(local)] = next_id
                self.session_of[next_id] = k
                next_id += 1
            self.of.append(mapping)


def rank_matches(
    query: PlaceDescriptor,
    references: Iterable[tuple[Any, PlaceDescriptor]],
    voxel_size_m: float,
    cfg: MergeConfig,
) -> list[tuple[int, Any, np.ndarray]]:
    """Descriptor matches of a query submap, best first: ``(RANSAC inliers, key, T_ref_query
    guess)`` for at most ``cfg.max_candidates_per_submap`` of the ``(key, descriptor)``
    references. Every reference gets a ratio-test match (a brute-force Hamming match, cheap);
    only the ``cfg.max_fits_per_submap`` with the most matches get a RANSAC fit."""
    shortlist = []
    for key, reference in references:
        index = ratio_matches(reference, query, cfg.ratio_test)
        if len(index) >= cfg.min_descriptor_inliers:
            shortlist.append((len(index), key, reference, index))
    shortlist.sort(key=lambda item: -item[0])
    ranked = []
    for _, key, reference, index in shortlist[: cfg.max_fits_per_submap]:
        guess, inliers = fit_matches(
            reference, query, index, cfg.descriptor_inlier_vu * voxel_size_m
        )
        if guess is not None and inliers >= cfg.min_descriptor_inliers:
            ranked.append((inliers, key, guess))
    ranked.sort(key=lambda item: -item[0])
    return ranked[: cfg.max_candidates_per_submap]


def _find_inter_loops(
    inputs: list[SessionInput], ids: _Ids, decoder: SurfaceDecoder, V: float, cfg: MergeConfig
) -> list[InterLoop]:
    submap_of = [{s.submap_id: s for s in item.submaps} for item in inputs]
    loops = []
    for k in range(1, len(inputs)):
        for q_local, q_desc in inputs[k].session.descriptors.items():
            if q_local not in submap_of[k] or q_local not in ids.of[k]:
                continue
            references = [
                ((m, r_local), r_desc)
                for m in range(k)
                for r_local, r_desc in inputs[m].session.descriptors.items()
                if r_local in submap_of[m] and r_local in ids.of[m]
            ]
            for inliers, (m, r_local), guess in rank_matches(q_desc, references, V, cfg):
                i, j = ids.of[m][r_local], ids.of[k][q_local]
                # keyed by run folder: a run given twice is decoded once
                reference = decoder((inputs[m].name, r_local), submap_of[m][r_local])
                query = decoder((inputs[k].name, q_local), submap_of[k][q_local])
                accepted, reason, T, scores, result = verify(reference, query, guess, V, cfg)
                scores["descriptor_inliers"] = float(inliers)
                loop = InterLoop(i, j, m, k, accepted, reason, T, scores)
                if accepted:
                    loop.covariance = icp_covariance(result, cfg)
                logger.info("inter-session %d-%d: %s", i, j, reason)
                loops.append(loop)
                if accepted:  # one edge per query submap: its best verified match
                    break
    return loops


def _initial_frames(
    inputs: list[SessionInput], ids: _Ids, loops: list[InterLoop]
) -> list[np.ndarray]:
    """``T_W0_Wk`` of every session from its best verified edge to a placed session."""
    T_W0_Wk: list[np.ndarray | None] = [np.eye(4)] + [None] * (len(inputs) - 1)
    anchors = [item.session.anchor_poses() for item in inputs]
    local = [{g: loc for loc, g in mapping.items()} for mapping in ids.of]
    accepted = sorted(
        (c for c in loops if c.accepted), key=lambda c: -c.scores.get("inlier_fraction", 0.0)
    )
    progress = True
    while progress and any(T is None for T in T_W0_Wk):
        progress = False
        for c in accepted:
            placed_i, placed_j = T_W0_Wk[c.session_i] is not None, T_W0_Wk[c.session_j] is not None
            if placed_i == placed_j:
                continue
            T_Wi_Ai = anchors[c.session_i][local[c.session_i][c.i]]
            T_Wj_Aj = anchors[c.session_j][local[c.session_j][c.j]]
            if placed_i:
                T = T_W0_Wk[c.session_i] @ T_Wi_Ai @ c.T_Ai_Aj @ np.linalg.inv(T_Wj_Aj)
                T_W0_Wk[c.session_j] = orthonormalize(T)
            else:
                T = (
                    T_W0_Wk[c.session_j]
                    @ T_Wj_Aj
                    @ np.linalg.inv(c.T_Ai_Aj)
                    @ np.linalg.inv(T_Wi_Ai)
                )
                T_W0_Wk[c.session_i] = orthonormalize(T)
            progress = True
    missing = [inputs[k].name for k, T in enumerate(T_W0_Wk) if T is None]
    if missing:
        examined = len(loops)
        raise MergeError(
            f"{', '.join(missing)}: shares no place with {inputs[0].name} or the other runs "
            f"({examined} inter-session candidates examined, none verified); nothing merged"
        )
    return [T for T in T_W0_Wk if T is not None]


def _noise(covariance: np.ndarray) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Gaussian.Covariance(np.asarray(covariance, dtype=np.float64))


def _solve(
    inputs: list[SessionInput],
    ids: _Ids,
    loops: list[InterLoop],
    T_W0_Wk: list[np.ndarray],
    cfg: MergeConfig,
) -> tuple[dict[int, np.ndarray], list[tuple[int, int, int]]]:
    """The joint graph solved by GNC; returns merged anchors and the stored loop factors."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    first = inputs[0].session
    g0 = ids.of[0][int(first.node_ids[0])]
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6))
    graph.add(gtsam.PriorFactorPose3(g0, pose3(first.T_W_A[0]), prior))
    intra: list[tuple[int, int, int]] = []
    for k, item in enumerate(inputs):
        for local, T in item.session.anchor_poses().items():
            values.insert(ids.of[k][local], pose3(T_W0_Wk[k] @ T))
        for edge in item.session.odometry + item.session.loops:
            i, j = ids.of[k][edge.i], ids.of[k][edge.j]
            measured = pose3(edge.T_Ai_Aj)
            graph.add(gtsam.BetweenFactorPose3(i, j, measured, _noise(edge.covariance)))
        intra += [(k, ids.of[k][e.i], ids.of[k][e.j]) for e in item.session.loops]
    _add_gravity(graph, values, inputs, ids)
    known = graph.size()
    accepted = [c for c in loops if c.accepted]
    for c in accepted:
        measured = pose3(c.T_Ai_Aj)
        graph.add(gtsam.BetweenFactorPose3(c.i, c.j, measured, _noise(c.covariance)))
    params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers(list(range(known)))
    optimizer = gtsam.GncLMOptimizer(graph, values, params)
    optimizer.setInlierCostThresholdsAtProbability(cfg.gnc_inlier_probability)
    result = optimizer.optimize()
    weights = np.asarray(optimizer.getWeights(), dtype=np.float64)[known:]
    for c, weight in zip(accepted, weights, strict=True):
        c.graph_inlier = bool(weight > 0.5)
    poses = {g: result.atPose3(g).matrix() for g in ids.session_of}
    return poses, intra


def _add_gravity(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, inputs: list[SessionInput], ids: _Ids
) -> None:
    """Every run's gravity factors against one gravity frame: gravity is the same for all."""
    measured = [(ids.of[k][n], m) for k, it in enumerate(inputs) for n, m in it.session.up.items()]
    if not measured:
        return
    first, measurement = measured[0]
    prior, T_W_G = gravity_frame_prior(GRAVITY_KEY, values.atPose3(first).matrix(), measurement)
    graph.add(prior)
    values.insert(GRAVITY_KEY, pose3(T_W_G))
    for node, m in measured:
        graph.add(gravity_factor(GRAVITY_KEY, node, T_W_G, values.atPose3(node).matrix(), m))


def merge_sessions(
    inputs: list[SessionInput], maps: list[NeuralMap], cfg: MergeConfig | None = None
) -> MergeResult:
    """Merge ``inputs`` (their loaded ``maps`` give config and prior) into one map and graph."""
    cfg = cfg or MergeConfig()
    if len(inputs) < 2:
        raise MergeError("give at least two run folders to merge")
    check_compatible(inputs, maps)
    seconds: dict[str, float] = {}
    V = maps[0].voxel_size_m
    ids = _Ids(inputs)
    start = time.perf_counter()
    decoder = SurfaceDecoder(maps[0], cfg.surface_max_points, cfg.surface_subdivisions)
    loops = _find_inter_loops(inputs, ids, decoder, V, cfg)
    seconds["inter_session_loops"] = time.perf_counter() - start
    T_W0_Wk = _initial_frames(inputs, ids, loops)
    start = time.perf_counter()
    T_W_A, intra = _solve(inputs, ids, loops, T_W0_Wk, cfg)
    seconds["pose_graph"] = time.perf_counter() - start
    start = time.perf_counter()
    merged_map = NeuralMap(maps[0].cfg, maps[0].model)
    submaps = []
    for k, item in enumerate(inputs):
        for s in item.submaps:
            g = ids.of[k].get(s.submap_id)
            if g is None:
                continue
            current = T_W0_Wk[k] @ s.T_W_A
            translation, rotation = relative_motion(current, T_W_A[g])
            small = translation <= cfg.remap_translation_m and rotation <= cfg.remap_rotation_deg
            # below the thresholds a submap stays where its run left it (a run remaps the same way)
            pose = (s.T_W_A if k == 0 else orthonormalize(current)) if small else T_W_A[g]
            placed = Submap(g, s.T_W_A_encoded, s.original, pose.copy())
            merged_map.fuse(placed)
            submaps.append(placed)
    seconds["remap"] = time.perf_counter() - start
    frame_poses = []
    for k, item in enumerate(inputs):
        anchors = {loc: T_W_A[g] for loc, g in ids.of[k].items()}
        frame_poses.append(item.session.frame_poses(anchors))
    session = _merged_session(inputs, ids, T_W_A, loops)
    return MergeResult(
        merged_map, submaps, T_W_A, T_W0_Wk, frame_poses, session, loops, intra, seconds
    )


def _merged_session(
    inputs: list[SessionInput], ids: _Ids, T_W_A: dict[int, np.ndarray], loops: list[InterLoop]
) -> SessionRecord:
    """The merged run as a session of its own (global ids; inter-session inliers as loops)."""
    node_ids = np.array(sorted(ids.session_of), dtype=np.int64)
    odometry, intra_loops, descriptors, parts, up = [], [], {}, [], {}
    frame_submap, frame_T_A_S, timestamps = [], [], []
    row = 0
    for k, item in enumerate(inputs):
        mapping = ids.of[k]
        s = item.session
        odometry += [Edge(mapping[e.i], mapping[e.j], e.T_Ai_Aj, e.covariance) for e in s.odometry]
        intra_loops += [Edge(mapping[e.i], mapping[e.j], e.T_Ai_Aj, e.covariance) for e in s.loops]
        descriptors.update({mapping[n]: d for n, d in s.descriptors.items() if n in mapping})
        up.update({mapping[n]: m for n, m in s.up.items()})
        frame_submap.append(np.array([mapping[int(n)] for n in s.frame_submap], dtype=np.int64))
        frame_T_A_S.append(s.frame_T_A_S)
        timestamps.append(s.timestamps)
        own = {"name": item.name, "first_row": 0, "rows": len(s.frame_submap)}
        for part in s.parts or [{**own, "session_id": s.session_id}]:
            parts.append({**part, "first_row": row + int(part["first_row"])})
        row += len(s.frame_submap)
    inter = [
        Edge(c.i, c.j, c.T_Ai_Aj, c.covariance) for c in loops if c.accepted and c.graph_inlier
    ]
    first = inputs[0].session
    return SessionRecord(
        setup={
            **first.setup,
            "merged": [item.name for item in inputs],
            "session_id": merged_session_id(inputs),
        },
        node_ids=node_ids,
        T_W_A=np.array([T_W_A[int(n)] for n in node_ids]),
        odometry=odometry,
        loops=intra_loops + inter,
        frame_submap=np.concatenate(frame_submap),
        frame_T_A_S=np.concatenate(frame_T_A_S),
        timestamps=np.concatenate(timestamps),
        descriptors=descriptors,
        dataset_mirror=first.dataset_mirror,
        parts=parts,
        up=up,
    )
