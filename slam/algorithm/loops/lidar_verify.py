"""LiDAR loop verification: a candidate pose between two submap clouds, refined and judged.

A candidate is refined by point-to-point ICP (KISS-ICP's registration against a voxel hash
map of the reference cloud, coarse then fine) and accepted only when

* for map_closures candidates: ICP did not have to move the candidate far (a large correction
  means the 2D match was wrong). Proximity candidates are judged by the result only: their
  correction is the accumulated drift, which is what the loop is for;
* enough query points lie close to the reference cloud after alignment (inlier ratio),
* the aligned clouds share enough voxels (overlap = shared voxels / voxels of the smaller cloud),
  and
* the cost is not flat: the smallest eigenvalue of the point-to-plane Hessian at the result
  (normals of the reference cloud; reported as ``min_eigenvalue``) shows that every direction is
  constrained. A featureless straight street lets ICP slide along it.

The same Hessian and the inlier residual give the edge's covariance
(:meth:`common.point_to_plane.IcpResult.covariance`).

The verifier also checks a candidate for ambiguity (re-registration from the other peaks of
the score along the street); see :mod:`slam.algorithm.loops.ambiguity`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from common.geometry import orthonormalize, relative_motion, transform_points
from common.normals import estimate_normals
from common.point_to_plane import point_to_plane_hessian, point_to_plane_icp
from common.voxel_keys import point_voxel_keys
from slam.algorithm.loops.ambiguity import find_ambiguity, inlier_score
from slam.algorithm.loops.base import Verification
from slam.algorithm.loops.config import LidarLoopConfig


def above_ground(points: np.ndarray, cell_m: float, clearance_m: float) -> np.ndarray:
    """Points more than ``clearance_m`` above the lowest point of their ``cell_m`` xy cell.

    LiDAR clouds are in a sensor frame with z up; the ground matches everywhere along a street,
    so the acceptance tests count only the structure standing on it.
    """
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    cells = np.floor(points[:, :2] / cell_m).astype(np.int64)
    _, inverse = np.unique(cells, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    lowest = np.full(inverse.max() + 1, np.inf)
    np.minimum.at(lowest, inverse, points[:, 2])
    return points[:, 2] > lowest[inverse] + clearance_m


def voxel_overlap(points_a: np.ndarray, points_b: np.ndarray, voxel_size_m: float) -> float:
    """Shared voxels of two clouds (same frame) over the voxels of the smaller one."""
    keys_a = np.unique(point_voxel_keys(points_a, voxel_size_m))
    keys_b = np.unique(point_voxel_keys(points_b, voxel_size_m))
    if len(keys_a) == 0 or len(keys_b) == 0:
        return 0.0
    shared = len(np.intersect1d(keys_a, keys_b, assume_unique=True))
    return shared / min(len(keys_a), len(keys_b))


class IcpVerifier:
    """Point-to-point ICP of a query cloud onto a reference cloud and the acceptance tests."""

    def __init__(self, cfg: LidarLoopConfig) -> None:
        self.cfg = cfg

    def align(
        self,
        reference: np.ndarray,
        query: np.ndarray,
        T_ref_query_guess: np.ndarray,
        scales: list[float] | None = None,
    ) -> np.ndarray:
        """Refine ``T_ref_query`` with KISS-ICP's robust point-to-point registration, coarse to
        fine: one pass per ``scales`` entry (default ``icp_scales``), each scaling the
        correspondence distance and the kernel (a guess off by a couple of degrees needs the
        wide first passes). Passes before the last two register the query thinned to
        ``icp_coarse_voxel_m``."""
        from kiss_icp.mapping import VoxelHashMap
        from kiss_icp.registration import Registration
        from kiss_icp.voxelization import voxel_down_sample

        c = self.cfg
        voxel_map = VoxelHashMap(
            voxel_size=c.overlap_voxel_m,
            max_distance=1e9,
            max_points_per_voxel=20,
        )
        voxel_map.add_points(np.asarray(reference, dtype=np.float64))
        registration = Registration(
            max_num_iterations=c.icp_max_iterations, convergence_criterion=1e-4, max_num_threads=1
        )
        points = np.asarray(query, dtype=np.float64)
        scales = c.icp_scales if scales is None else scales
        coarse = points
        if c.icp_coarse_voxel_m > 0 and len(scales) > 2:
            coarse = np.asarray(voxel_down_sample(points, c.icp_coarse_voxel_m), dtype=np.float64)
        T = orthonormalize(T_ref_query_guess)
        for k, scale in enumerate(scales):
            T = np.asarray(
                registration.align_points_to_map(
                    points=coarse if k < len(scales) - 2 else points,
                    voxel_map=voxel_map,
                    initial_guess=T,
                    max_correspondance_distance=scale * c.icp_max_correspondence_m,
                    kernel=scale * c.icp_kernel_m,
                ),
                dtype=np.float64,
            )
        return T

    def verify(
        self,
        reference: np.ndarray,
        query: np.ndarray,
        T_ref_query_guess: np.ndarray,
        limit_correction: bool = True,
        check_ambiguity: bool = True,
        graph_check: Callable[[Verification], Verification] | None = None,
    ) -> Verification:
        """ICP plus the acceptance tests; an accepted edge carries its ICP covariance.

        ``limit_correction``: reject a large ICP correction (for guesses that are independent
        of the drift, such as map_closures' 2D matches). ``graph_check``: then judges an
        accepted edge against the pose graph. ``check_ambiguity``: finally the ambiguity search
        of :meth:`_check_ambiguity` (when ``cfg.ambiguity_check``), on the clouds, structure and
        normals prepared here.
        """
        c = self.cfg
        full_reference = np.asarray(reference, dtype=np.float64)
        full_query = np.asarray(query, dtype=np.float64)
        T = self.align(full_reference, full_query, T_ref_query_guess)
        correction_m, correction_deg = relative_motion(T_ref_query_guess, T)
        scores = {"icp_correction_m": correction_m, "icp_correction_deg": correction_deg}
        if not np.all(np.isfinite(T)):
            return Verification(False, "icp diverged", T_ref_query_guess, scores)
        reference, query = self._structure(full_reference), self._structure(full_query)
        scores["structure_points"] = float(min(len(reference), len(query)))
        if min(len(reference), len(query)) < c.min_structure_points:
            return Verification(False, "too little structure above the ground", T, scores)
        clouds = _Clouds(
            full_reference,
            full_query,
            reference,
            query,
            cKDTree(reference),
            _Surfaces.of(full_reference, c.inlier_distance_m),
            c.inlier_distance_m,
        )
        T, flags = self._refine(clouds, T_ref_query_guess, T)
        correction_m, correction_deg = relative_motion(T_ref_query_guess, T)
        scores.update(flags, icp_correction_m=correction_m, icp_correction_deg=correction_deg)
        inlier_ratio = clouds.score(T)
        overlap = voxel_overlap(reference, transform_points(T, query), c.overlap_voxel_m)
        scores["inlier_ratio"] = inlier_ratio
        scores["overlap"] = overlap
        surfaces = clouds.surfaces
        cost = point_to_plane_hessian(
            surfaces.points,
            surfaces.normals,
            full_query,
            T,
            max_distance_m=c.inlier_distance_m,
            tree=surfaces.tree,
        )
        eigenvalue = cost.normalized_min_eigenvalue(_rms_radius(full_reference))
        scores["min_eigenvalue"] = eigenvalue
        if limit_correction and (
            correction_m > c.max_icp_correction_m or correction_deg > c.max_icp_correction_deg
        ):
            reason = f"icp correction {correction_m:.2f} m / {correction_deg:.1f} deg too large"
            return Verification(False, reason, T, scores)
        if inlier_ratio < c.min_inlier_ratio:
            reason = f"inlier ratio {inlier_ratio:.2f} < {c.min_inlier_ratio:.2f}"
            return Verification(False, reason, T, scores)
        if overlap < c.min_overlap:
            return Verification(False, f"overlap {overlap:.2f} < {c.min_overlap:.2f}", T, scores)
        if eigenvalue < c.min_hessian_eigenvalue:
            reason = (
                f"degenerate icp cost: min eigenvalue {eigenvalue:.4f} < {c.min_hessian_eigenvalue}"
            )
            return Verification(False, reason, T, scores)
        verification = Verification(
            True, "accepted", T, scores, cost.covariance(c.covariance_factor)
        )
        if graph_check is not None:
            verification = graph_check(verification)
        if check_ambiguity:
            verification = self._check_ambiguity(clouds, verification)
        return verification

    def _structure(self, points: np.ndarray) -> np.ndarray:
        c = self.cfg
        if c.ground_clearance_m <= 0:
            return points
        return points[above_ground(points, c.ground_cell_m, c.ground_clearance_m)]

    def _check_ambiguity(self, clouds: _Clouds, verification: Verification) -> Verification:
        """Reject an accepted ``verification`` when another registration scores about as well
        (:func:`slam.algorithm.loops.ambiguity.find_ambiguity`), on the structure above the
        ground; the profile reaches the reference structure's RMS radius at most."""
        c = self.cfg
        if not (c.ambiguity_check and verification.accepted):
            return verification

        def realign(guess: np.ndarray) -> np.ndarray:
            """The fine passes, polished like the chosen solution (so both compete alike)."""
            T = self.align(clouds.reference, clouds.query, guess, scales=c.icp_scales[-2:])
            if not (c.icp_point_to_plane and np.all(np.isfinite(T))):
                return T
            polished = self._polish(clouds.query, T, clouds.surfaces)
            return T if polished is None else polished

        score, alternative = find_ambiguity(
            clouds.reference_structure,
            clouds.query_structure,
            verification.T_ref_query,
            verification.covariance,
            realign,
            inlier_distance_m=c.inlier_distance_m,
            step_m=c.ambiguity_step_m,
            max_offset_m=min(c.ambiguity_max_offset_m, _rms_radius(clouds.reference_structure)),
            min_separation_m=c.ambiguity_min_separation_m,
            min_separation_deg=c.ambiguity_min_separation_deg,
            max_realignments=c.ambiguity_max_realignments,
            tree=clouds.structure_tree,
        )
        scores = dict(verification.scores)
        scores["ambiguity_score"] = score
        if alternative is None:
            scores["ambiguity_alternative_score"] = 0.0
            return verification._replace(scores=scores)
        scores["ambiguity_alternative_score"] = alternative.score
        scores["ambiguity_separation_m"] = alternative.separation_m
        if alternative.score >= c.ambiguity_score_ratio * score:
            reason = (
                f"ambiguous: a solution {alternative.separation_m:.2f} m / "
                f"{alternative.separation_deg:.1f} deg away scores {alternative.score:.2f} vs "
                f"{score:.2f}"
            )
            return Verification(False, reason, verification.T_ref_query, scores)
        return verification._replace(scores=scores)

    def _refine(
        self, clouds: _Clouds, guess: np.ndarray, T: np.ndarray
    ) -> tuple[np.ndarray, dict[str, float]]:
        """The registration to judge, from the coarse-to-fine ICP result ``T``, and flags saying
        which refinements changed it.

        ``icp_fine_restart``: the fine passes alone from ``guess`` (when ``T`` moved it by the
        ``icp_fine_restart_min_correction_*``), kept when their result scores more inliers.
        ``icp_point_to_plane``: then point-to-plane ICP on the reference's surfaces, which
        KISS-ICP's point-to-point cost does not see: on the generated sparse street it took
        loops that point-to-point left 0.7-1.1 deg off to within 0.1 deg, with as many inliers
        as the true pose.
        """
        c = self.cfg
        flags: dict[str, float] = {}
        moved_m, moved_deg = relative_motion(guess, T)
        if (
            c.icp_fine_restart
            and len(c.icp_scales) > 2
            and (
                moved_m >= c.icp_fine_restart_min_correction_m
                or moved_deg >= c.icp_fine_restart_min_correction_deg
            )
        ):
            T_fine = self.align(clouds.reference, clouds.query, guess, scales=c.icp_scales[-2:])
            if np.all(np.isfinite(T_fine)) and clouds.score(T_fine) > clouds.score(T):
                T, flags["icp_fine_restart"] = T_fine, 1.0
        if c.icp_point_to_plane:
            polished = self._polish(clouds.query, T, clouds.surfaces)
            if polished is not None:
                T, flags["icp_point_to_plane"] = polished, 1.0
        return T, flags

    def _polish(self, query: np.ndarray, T: np.ndarray, surfaces: _Surfaces) -> np.ndarray | None:
        """Point-to-plane ICP from ``T`` (None when it found no correspondences)."""
        d = self.cfg.inlier_distance_m
        result = point_to_plane_icp(
            surfaces.points,
            surfaces.normals,
            query,
            T,
            max_distances_m=(2 * d, d, d / 2),
            max_iterations=20,
            tree=surfaces.tree,
        )
        if result.num_inliers > 0 and np.all(np.isfinite(result.T_ref_query)):
            return result.T_ref_query
        return None


@dataclass
class _Surfaces:
    """Reference points with PCA normals (the point-to-plane ICP and Hessian) and their tree."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree

    @staticmethod
    def of(reference: np.ndarray, inlier_distance_m: float) -> _Surfaces:
        normals, valid = estimate_normals(
            reference, np.zeros(3), num_neighbours=10, max_radius_m=4 * inlier_distance_m
        )
        return _Surfaces(reference[valid], normals[valid], cKDTree(reference[valid]))


@dataclass
class _Clouds:
    """One candidate's clouds and what its verification derives from them, each made once.

    Attributes:
        reference, query: the whole clouds (float64).
        reference_structure, query_structure: their points above the ground (the scores').
        structure_tree: KD-tree of ``reference_structure``.
        surfaces: the reference's points with normals (point-to-plane ICP and Hessian).
        inlier_distance_m: a query point within this of the reference structure is an inlier.
    """

    reference: np.ndarray
    query: np.ndarray
    reference_structure: np.ndarray
    query_structure: np.ndarray
    structure_tree: cKDTree
    surfaces: _Surfaces
    inlier_distance_m: float

    def score(self, T_ref_query: np.ndarray) -> float:
        """Inlier score of the query structure against the reference's after ``T_ref_query``."""
        return inlier_score(
            self.structure_tree, self.query_structure, T_ref_query, self.inlier_distance_m
        )


def _rms_radius(points: np.ndarray) -> float:
    if len(points) == 0:
        return 1.0
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))
