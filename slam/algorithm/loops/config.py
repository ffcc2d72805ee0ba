"""Configuration of loop closure: candidates, verification and acceptance gates of the LiDAR
(:mod:`slam.algorithm.loops.lidar`, :mod:`slam.algorithm.loops.ambiguity`) and RGB-D
(:mod:`slam.algorithm.loops.rgbd`) detectors. Unknown keys are errors."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from common.config import Strict


class LidarLoopConfig(Strict):
    """LiDAR loop closure: map_closures candidates verified by ICP and voxel overlap."""

    density_map_resolution_m: float = Field(
        0.5,
        ge=0.01,
        description="map_closures BEV density image resolution (at least 1 cm: the image grows "
        "with its square)",
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
    top_k: int = Field(
        3,
        ge=1,
        le=100,
        description="map_closures candidates verified per query submap; at most 100",
    )
    proximity_radius_m: float = Field(
        0.0,
        ge=0,
        description="also verify older anchors whose estimate is this close (0: map_closures only)",
    )
    max_proximity_candidates: int = Field(
        2,
        ge=1,
        le=100,
        description="nearest proximity candidates verified per query submap; at most 100",
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
        "can settle up to 1 deg off on sparse streets (slam/algorithm/loops/lidar_verify.py)",
    )
    icp_max_iterations: int = Field(
        200, ge=1, le=10_000, description="ICP iterations; at most 10,000"
    )
    overlap_voxel_m: float = Field(
        1.0,
        ge=0.01,
        description="grid of the overlap test between the aligned submap clouds (at least 1 cm)",
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
    ground_cell_m: float = Field(
        4.0, ge=0.01, description="xy cell size of that ground estimate (at least 1 cm)"
    )
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
        "about as well (slam/algorithm/loops/ambiguity.py)",
    )
    ambiguity_step_m: float = Field(
        0.5,
        ge=0.01,
        description="grid step of the inlier-score profile along each direction (at least 1 cm)",
    )
    ambiguity_max_offset_m: float = Field(
        25.0,
        gt=0,
        le=1000,
        description="the profile reaches this far, or the RMS radius of the reference structure "
        "when that is smaller (beyond it the clouds barely overlap); at most 1000 m",
    )
    ambiguity_min_separation_m: float = Field(
        1.0, gt=0, description="an alternative solution lies at least this far from the chosen one"
    )
    ambiguity_min_separation_deg: float = Field(
        2.0, gt=0, description="... or is rotated at least this much from it"
    )
    ambiguity_max_realignments: int = Field(
        2,
        ge=1,
        le=100,
        description="profile peaks re-registered per accepted candidate (ICP runs); at most 100",
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


class RgbdLoopConfig(Strict):
    """RGB-D loop closure: pose proximity + ORB, PnP-RANSAC, cv2.Odometry, dense ICP."""

    candidate_radius_m: float = Field(
        2.0, gt=0, description="reference anchors within this distance of the query are candidates"
    )
    max_candidates: int = Field(
        3, ge=1, le=100, description="best-matching candidates verified; at most 100"
    )
    orb_features: int = Field(
        1000, ge=100, le=100_000, description="ORB features per keyframe; at most 100,000"
    )
    ratio_test: float = Field(0.8, gt=0, le=1, description="Lowe ratio test of ORB matches")
    min_matches: int = Field(30, ge=6, description="minimum ORB matches of a candidate")
    pnp_reprojection_px: float = Field(
        3.0, gt=0, description="PnP-RANSAC inlier reprojection threshold"
    )
    min_pnp_inliers: int = Field(25, ge=6, description="minimum PnP-RANSAC inliers")
    min_inlier_ratio: float = Field(
        0.3, gt=0, le=1, description="minimum PnP inliers / matches with depth"
    )
    max_3d_residual_m: float = Field(
        0.05, gt=0, description="3D-3D check: median inlier residual with both depths"
    )
    max_refine_disagreement_m: float = Field(
        0.1, gt=0, description="reject when cv2.Odometry moves the PnP pose more than this"
    )
    max_refine_disagreement_deg: float = Field(
        5.0, gt=0, description="reject when cv2.Odometry rotates the PnP pose more than this"
    )
    depth_inlier_distance_m: float = Field(
        0.03,
        gt=0,
        description="depth agreement: a reference depth pixel moved into the query view agrees "
        "with the query depth within this distance",
    )
    min_depth_agreement: float = Field(
        0.5,
        gt=0,
        le=1,
        description="cv2.Odometry's pose, and the final edge, need at least this fraction of the "
        "overlapping depth pixels to agree",
    )
    max_depth_residual_m: float = Field(
        0.02,
        gt=0,
        description="... and a median depth disagreement of the overlapping pixels below this",
    )
    refine: bool = Field(
        True,
        description="refine every verified edge by point-to-plane ICP between the two submaps' "
        "clouds (the edge then depends on depth only) and check that registration too",
    )
    refine_voxel_m: float = Field(
        0.03,
        ge=0.001,
        description="voxel size the submap clouds are thinned to for the refinement (at least 1 "
        "mm)",
    )
    refine_max_points: int = Field(
        8000,
        ge=100,
        le=10_000_000,
        description="at most this many points per cloud in the refinement; at most 10,000,000",
    )
    refine_max_distances_m: list[float] = Field(
        default_factory=lambda: [0.1, 0.05, 0.025],
        min_length=1,
        description="coarse-to-fine correspondence gates of the refinement ICP",
    )
    refine_min_inlier_fraction: float = Field(
        0.15,
        gt=0,
        le=1,
        description="reject when fewer query points than this lie within the finest gate (two "
        "submaps overlap only in part: the keyframe depth agreement is the stricter test)",
    )
    refine_max_residual_m: float = Field(
        0.012,
        gt=0,
        description="reject when the robust spread (1.4826 x median absolute value) of the "
        "inliers' point-to-plane residuals is larger (or larger than 0.4 x the finest gate, "
        "which widens to 1.5 x the point spacing for sparse clouds)",
    )
    refine_max_correction_m: float = Field(
        0.1, gt=0, description="reject when the refinement moves the edge further than this"
    )
    refine_max_correction_deg: float = Field(
        5.0, gt=0, description="reject when the refinement rotates the edge more than this"
    )
    refine_min_eigenvalue: float = Field(
        0.015,
        ge=0,
        description="reject when the smallest eigenvalue of the refinement's normalised "
        "Hessian (rotation scaled by the cloud's RMS radius; about the fraction of points "
        "constraining the weakest direction) is below this: a flat or degenerate cost. "
        "Measured on 7-Scenes: edges below 0.015 were 7-13 cm off the ground truth while "
        "their depth agreed no better than the ground truth's (the cost could not fix them); "
        "a single plane gives 0, the generated room's loop 0.022",
    )
    keyframe_refine: bool = Field(
        True,
        description="after the submap ICP, refine the edge once more by point-to-plane ICP "
        "between the two anchor keyframes' own depth clouds, from the submap ICP's result, and "
        "make that the edge (its ICP checks as for the submap ICP, then the keyframe depth "
        "agreement; a failure rejects the loop). A submap cloud is fused with its frames' "
        "estimated poses, so their errors bend it and the pose that aligns two whole submaps "
        "best is not the anchors' relative pose; measured on 7-Scenes: loop error median "
        "4.5 -> 2.8 cm against the ground truth, SLAM ATE 4.0 -> 2.6 cm; on the generated room "
        "(exact depth) SLAM ATE 0.38 -> 0.37 cm but mesh accuracy 0.51 -> 0.58 cm",
    )
    keyframe_refine_stride_px: int = Field(
        4,
        ge=1,
        description="keyframe refinement: every stride-th depth pixel (rows and columns) is "
        "lifted (7-Scenes, 640x480: stride 4 registered as well as stride 2, in 0.56 s a pair "
        "instead of 1.4 s)",
    )
    keyframe_refine_voxel_m: float = Field(
        0.01,
        ge=0.001,
        description="keyframe refinement: voxel size the keyframe clouds are thinned to (at least "
        "1 mm)",
    )
    keyframe_refine_max_points: int = Field(
        20000,
        ge=100,
        le=10_000_000,
        description="keyframe refinement: at most this many points per keyframe; at most "
        "10,000,000",
    )
    proximity_candidates: int = Field(
        2,
        ge=0,
        le=100,
        description="also try this many nearest older anchors (within candidate_radius_m) by "
        "dense refinement alone from their current relative estimate (0: ORB candidates only); at "
        "most 100",
    )
    proximity_max_angle_deg: float = Field(
        45.0,
        gt=0,
        le=180,
        description="proximity candidates: largest angle between the two keyframes' optical axes",
    )
    covariance_factor: float = Field(
        10.0,
        gt=0,
        description="the loop covariance is this factor times the ICP estimate sigma^2 H^-1 "
        "(neighbouring residuals are correlated and the clouds carry odometry drift, so the raw "
        "estimate is over-confident)",
    )
    min_depth_m: float = Field(0.1, ge=0, description="valid depth range, lower bound")
    max_depth_m: float = Field(8.0, gt=0, description="valid depth range, upper bound")


class LoopClosureConfig(Strict):
    """Loop detection and verification."""

    enabled: bool = Field(True, description="detect loop closures at all")
    method: Literal["auto", "lidar", "rgbd"] = Field(
        "auto", description="'auto' follows the sensor of the source"
    )
    min_submap_separation: int = Field(
        3, ge=1, description="a reference submap must be at least this many submaps older"
    )
    min_travel_m: float = Field(
        3.0, ge=0, description="path length between query and reference anchors must exceed this"
    )
    lidar: LidarLoopConfig = Field(default_factory=LidarLoopConfig, description="LiDAR loops")
    rgbd: RgbdLoopConfig = Field(default_factory=RgbdLoopConfig, description="RGB-D loops")
