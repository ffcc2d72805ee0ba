"""Surfaces decoded from a submap's own neural map, and their verification by ICP.

A merge (and a localisation) never sees scans: each submap's surface is meshed from its original
encoding alone (:class:`SurfaceDecoder`), and a candidate's relative pose is refined and judged by
point-to-plane ICP between two such surfaces (:func:`verify`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.spatial import cKDTree

from common.geometry import relative_motion, transform_points
from common.point_to_plane import IcpResult, point_to_plane_hessian, point_to_plane_icp
from mapping.neural_map import NeuralMap, Submap
from slam.algorithm.merge.config import MergeConfig

COARSE_GATE_VU = 0.5
"""ICP gates wider than this (voxel units) are coarse (:func:`align_surfaces`)."""
SURFACE_CHUNKS_PER_BATCH = 256
"""Mesh chunks decoded together when a surface is decoded: a voxel feeding chunks in two batches
is decoded in both (:meth:`mapping.meshing.ChunkMesher.update`); the quick street map's submaps
(about 280 chunks each) decoded 1.21 times their voxels at the run's 32, in a tenth more time;
at 256 a decoding thread peaks 35 MiB higher."""


class SurfaceDecoder:
    """Surface points with normals of a submap in its anchor frame, decoded from its own latents.

    Each surface is decoded once and cached by its key. :meth:`decode_many` decodes several on
    a pool of threads (torch releases the GIL), each running torch with its intra-op threads."""

    def __init__(self, neural_map: NeuralMap, max_points: int, subdivisions: int) -> None:
        self._cfg = neural_map.cfg.model_copy(update={"mesh_subdivisions": subdivisions})
        self._model = neural_map.model
        self._max_points = max_points
        self._cache: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, key: tuple[str, int], submap: Submap) -> tuple[np.ndarray, np.ndarray]:
        if key not in self._cache:
            self._cache[key] = self._decode(submap)
        return self._cache[key]

    def decode_many(self, items: list[tuple[tuple[str, int], Submap]], threads: int) -> None:
        """Decode and cache every ``(key, submap)`` not cached yet, on ``threads`` threads."""
        missing = [(key, submap) for key, submap in items if key not in self._cache]
        with ThreadPoolExecutor(max_workers=max(1, threads), thread_name_prefix="decode") as pool:
            surfaces = pool.map(self._decode, [submap for _, submap in missing])
            for (key, _), surface in zip(missing, surfaces, strict=True):
                self._cache[key] = surface

    def _decode(self, submap: Submap) -> tuple[np.ndarray, np.ndarray]:
        alone = NeuralMap(self._cfg, self._model)
        copy = Submap(submap.submap_id, submap.T_W_A_encoded, submap.original, submap.T_W_A_encoded)
        alone.fuse(copy)
        mesh = alone.extract_mesh(chunks_per_batch=SURFACE_CHUNKS_PER_BATCH)
        points = np.asarray(mesh.vertices, dtype=np.float64)
        normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
        if len(points) > self._max_points:
            pick = np.sort(
                np.random.default_rng(0).choice(len(points), self._max_points, replace=False)
            )
            points, normals = points[pick], normals[pick]
        T_A_W = np.linalg.inv(submap.T_W_A_encoded)
        return transform_points(T_A_W, points), normals @ T_A_W[:3, :3].T


def icp_covariance(result, cfg: MergeConfig) -> np.ndarray:
    floor = np.array([cfg.loop_min_sigma_rad] * 3 + [cfg.loop_min_sigma_m] * 3) ** 2
    return result.covariance(cfg.covariance_factor) + np.diag(floor)


def _overlap(
    reference: tuple[np.ndarray, np.ndarray],
    query: np.ndarray,
    T: np.ndarray,
    gate_m: float,
    tree: cKDTree,
) -> tuple[float, float]:
    """Fraction of ``query`` within ``gate_m`` of the reference surface under ``T``, and the
    robust spread of those points' point-to-plane residuals (the cost seen at ``T``,
    :func:`~common.point_to_plane.point_to_plane_hessian`)."""
    if not np.all(np.isfinite(T)):
        return 0.0, float("inf")
    seen = point_to_plane_hessian(reference[0], reference[1], query, T, gate_m, tree=tree)
    return seen.inlier_fraction, seen.robust_sigma_m


def align_surfaces(
    reference: tuple[np.ndarray, np.ndarray],
    query: np.ndarray,
    guess: np.ndarray,
    voxel_size_m: float,
    cfg: MergeConfig,
    tree: cKDTree,
    coarse_query: np.ndarray | None = None,
) -> IcpResult:
    """Point-to-plane ICP of ``query`` onto a decoded surface (its points and normals, ``tree``
    their KD-tree) from ``guess`` through the gates ``icp_gates_vu``. With ``coarse_query`` (a
    subset of ``query``) the gates wider than half a voxel align that subset alone: they only
    bring the pose into the fine gates' reach, which then align every point, and the KD-tree
    queries of the coarse iterations (about three fifths of them) cost a fraction
    (``LocaliseConfig.coarse_query_points``)."""
    V = voxel_size_m
    gates = tuple(g * V for g in cfg.icp_gates_vu)
    tolerance = cfg.icp_tolerance_vu * V
    coarse = tuple(g for g in gates if g > COARSE_GATE_VU * V)
    fine = tuple(g for g in gates if g <= COARSE_GATE_VU * V)
    if coarse_query is not None and coarse and fine:
        guess = point_to_plane_icp(
            reference[0], reference[1], coarse_query, guess, coarse, tolerance=tolerance, tree=tree
        ).T_ref_query
        gates = fine
    return point_to_plane_icp(
        reference[0], reference[1], query, guess, gates, tolerance=tolerance, tree=tree
    )


def verify(
    reference: tuple[np.ndarray, np.ndarray],
    query: tuple[np.ndarray, np.ndarray],
    guess: np.ndarray,
    voxel_size_m: float,
    cfg: MergeConfig,
    tree: cKDTree | None = None,
    coarse_query: np.ndarray | None = None,
):
    """ICP of decoded surfaces from a guess: ``(accepted, reason, T_ref_query, scores, result)``;
    ``tree``: a KD-tree of the reference points already built (else one is); ``coarse_query``:
    the points the gates wider than half a voxel align (a subset of ``query[0]``; else all), see
    :func:`align_surfaces`.

    The ICP's gates narrow down to ``icp_gates_vu[-1]``: a wide last gate lets the parts of two
    partly overlapping surfaces that do not match pull the pose (measured on 7-Scenes redkitchen:
    ending at 0.75 voxel, the kept edges were up to 7.3 cm / 2.1 deg off the ground truth and the
    merged trajectory 1.48 x one run's ATE; ending at 0.25, as the run's own loop refinement does,
    4.9 cm and 1.19 x). Overlap and residual are judged at ``overlap_gate_vu`` instead, so a
    finer pose does not change what is accepted."""
    V = voxel_size_m
    tree = tree if tree is not None else cKDTree(reference[0])
    result = align_surfaces(reference, query[0], guess, V, cfg, tree, coarse_query)
    T = result.T_ref_query
    overlap, residual = _overlap(reference, query[0], T, cfg.overlap_gate_vu * V, tree)
    correction_m, correction_deg = relative_motion(guess, T)
    radius = float(np.sqrt(np.mean(np.sum((reference[0] - reference[0].mean(0)) ** 2, axis=1))))
    eigenvalue = result.normalized_min_eigenvalue(radius)
    scores = {
        "inlier_fraction": overlap,
        "residual_sigma_m": residual,
        "correction_m": correction_m,
        "correction_deg": correction_deg,
        "min_eigenvalue": eigenvalue,
    }
    if not np.all(np.isfinite(T)) or not np.isfinite(residual):
        return False, "icp found no correspondences", guess, scores, result
    if overlap < cfg.min_inlier_fraction:
        reason = f"inlier fraction {overlap:.2f} < {cfg.min_inlier_fraction:.2f}"
        return False, reason, T, scores, result
    if residual > cfg.max_residual_vu * V:
        reason = f"residual {residual:.4f} m > {cfg.max_residual_vu * V:.4f} m"
        return False, reason, T, scores, result
    if correction_m > cfg.max_correction_vu * V or correction_deg > cfg.max_correction_deg:
        reason = f"correction {correction_m:.3f} m / {correction_deg:.1f} deg too large"
        return False, reason, T, scores, result
    if eigenvalue < cfg.min_eigenvalue:
        return False, f"degenerate cost: min eigenvalue {eigenvalue:.4f}", T, scores, result
    return True, "accepted", T, scores, result
