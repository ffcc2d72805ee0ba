"""Configuration of LiDAR loop closure (:mod:`slam.algorithm.loop_lidar` and
:mod:`slam.algorithm.loop_ambiguity`): candidates, ICP, acceptance gates and the ambiguity and
graph checks. Part of :class:`slam.algorithm.config.LoopClosureConfig`; unknown keys are errors,
as everywhere in :mod:`slam.algorithm.config`.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class LidarLoopConfig(BaseModel):
    """LiDAR loop closure: map_closures candidates verified by ICP and voxel overlap."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    density_map_resolution_m: float = Field(
        0.5, gt=0, description="map_closures BEV density image resolution"
    )
    density_threshold: float = Field(
        0.05, ge=0, description="map_closures density threshold of an occupied BEV cell"
    )
    hamming_distance_threshold: int = Field(
        50, ge=1, description="map_closures ORB descriptor matching threshold"
    )
    inliers_threshold: int = Field(
        5, ge=3, description="minimum 2D RANSAC inliers of a map_closures candidate"
    )
    top_k: int = Field(3, ge=1, description="map_closures candidates verified per query submap")
    proximity_radius_m: float = Field(
        0.0,
        ge=0,
        description="also verify older anchors whose estimate is this close (0: map_closures only)",
    )
    max_proximity_candidates: int = Field(
        2, ge=1, description="nearest proximity candidates verified per query submap"
    )
    icp_max_correspondence_m: float = Field(2.0, gt=0, description="ICP correspondence distance")
    icp_kernel_m: float = Field(0.5, gt=0, description="ICP robust kernel scale")
    icp_scales: list[float] = Field(
        default_factory=lambda: [5.0, 2.0, 1.0, 0.5],
        min_length=1,
        description="coarse-to-fine ICP passes: factors on the correspondence distance and kernel",
    )
    icp_coarse_voxel_m: float = Field(
        1.0,
        ge=0,
        description="the passes before the last two register the query thinned to one point per "
        "voxel of this size (0: every point); they only bring the guess into the fine passes' "
        "reach, and the widest pass was 40 % of the ICP time",
    )
    icp_fine_restart: bool = Field(
        True,
        description="also refine the guess with the last two ICP scales alone and keep the "
        "result with the higher inlier ratio: the wide first passes can drag a good guess into a "
        "worse minimum (generated sparse street, loop 9-58: 1.53 deg wrong, 0.59 inliers; from "
        "the guess with the fine passes: 0.77 deg, 0.68)",
    )
    icp_fine_restart_min_correction_m: float = Field(
        0.25,
        ge=0,
        description="restart only when the coarse-to-fine result lies at least this far from the "
        "guess (or icp_fine_restart_min_correction_deg): closer, the fine passes from the guess "
        "converged to the same pose on every stored loop of the generated streets",
    )
    icp_fine_restart_min_correction_deg: float = Field(
        0.25, ge=0, description="... or is rotated at least this much from it"
    )
    icp_point_to_plane: bool = Field(
        True,
        description="finish the registration with point-to-plane ICP on the reference cloud's "
        "PCA normals (gates 2, 1 and 0.5 x inlier_distance_m): KISS-ICP's point-to-point cost "
        "can settle up to 1 deg off on sparse streets (slam/algorithm/loop_lidar.py)",
    )
    icp_max_iterations: int = Field(200, ge=1, description="ICP iterations")
    overlap_voxel_m: float = Field(
        1.0, gt=0, description="grid of the overlap test between the aligned submap clouds"
    )
    min_overlap: float = Field(
        0.4,
        gt=0,
        le=1,
        description="accept when shared voxels / smaller cloud (above the ground) is at least this",
    )
    inlier_distance_m: float = Field(
        0.5, gt=0, description="a query point is an ICP inlier within this distance"
    )
    ground_clearance_m: float = Field(
        0.5,
        ge=0,
        description="inlier ratio and overlap count only points this far above the lowest "
        "point of their xy cell (the ground matches anywhere along a street); 0: all points",
    )
    ground_cell_m: float = Field(4.0, gt=0, description="xy cell size of that ground estimate")
    min_structure_points: int = Field(
        100, ge=1, description="reject when either cloud has fewer points above the ground"
    )
    min_inlier_ratio: float = Field(
        0.5,
        gt=0,
        le=1,
        description="accept when this fraction of the query cloud (above the ground) are inliers",
    )
    max_icp_correction_m: float = Field(
        5.0,
        gt=0,
        description="reject a map_closures candidate when ICP moves its pose by more than this "
        "(a wrong 2D match); proximity candidates are judged by the result only (their "
        "correction is the drift)",
    )
    max_icp_correction_deg: float = Field(
        15.0,
        gt=0,
        description="reject a map_closures candidate when ICP rotates its pose by more than this",
    )
    min_hessian_eigenvalue: float = Field(
        0.002,
        ge=0,
        description="reject when the smallest eigenvalue of the point-to-plane Hessian at the "
        "ICP result (per inlier, rotation scaled by the reference cloud's RMS radius; about the "
        "fraction of correspondences constraining the weakest direction) is below this: a flat "
        "or degenerate cost, e.g. a featureless straight street",
    )
    covariance_factor: float = Field(
        10.0,
        gt=0,
        description="the loop covariance is this factor times sigma^2 H^-1 of that Hessian "
        "(sigma: point-to-plane RMSE of the inliers)",
    )
    ambiguity_check: bool = Field(
        True,
        description="re-register from the best other peaks of the inlier score along the street "
        "and along the weakest Hessian direction; reject when one converges elsewhere and scores "
        "about as well (slam/algorithm/loop_ambiguity.py)",
    )
    ambiguity_step_m: float = Field(
        0.5, gt=0, description="grid step of the inlier-score profile along each direction"
    )
    ambiguity_max_offset_m: float = Field(
        25.0,
        gt=0,
        description="the profile reaches this far, or the RMS radius of the reference structure "
        "when that is smaller (beyond it the clouds barely overlap)",
    )
    ambiguity_min_separation_m: float = Field(
        1.0, gt=0, description="an alternative solution lies at least this far from the chosen one"
    )
    ambiguity_min_separation_deg: float = Field(
        2.0, gt=0, description="... or is rotated at least this much from it"
    )
    ambiguity_max_realignments: int = Field(
        2, ge=1, description="profile peaks re-registered per accepted candidate (ICP runs)"
    )
    ambiguity_score_ratio: float = Field(
        0.9,
        gt=0,
        description="ambiguous when an alternative's inlier score is at least this fraction of "
        "the chosen solution's (periodic street: true 0.99, one period off 0.73-0.79)",
    )
    graph_consistency_probability: float = Field(
        0.9999,
        ge=0,
        lt=1,
        description="reject when the registered relative pose lies outside this chi-square "
        "quantile (6 dof) of the pose graph's marginal covariance of that relative pose plus "
        "the registration's own; 0: off",
    )
