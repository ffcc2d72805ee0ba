"""Configuration of the algorithm: keyframing, loop closure, pose graph and remapping.

One pydantic model per stage; every model forbids unknown keys, so a typo in a YAML file is an
error that names the key. The run's configuration (:class:`slam.app.config.RunConfig`) composes
these with the sources, odometry, map, viewer and output settings.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from slam.algorithm.lidar_loop_config import LidarLoopConfig


class Strict(BaseModel):
    """Base of every config model: unknown keys are errors, assignments are validated."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class SubmapConfig(Strict):
    """Keyframing: when a submap closes and how its points are kept."""

    max_distance_m: float = Field(
        2.0, gt=0, description="close the submap when the sensor is this far from the anchor"
    )
    max_rotation_deg: float = Field(
        30.0, gt=0, description="close the submap when the sensor turned this much from the anchor"
    )
    max_frames: int = Field(30, ge=1, description="close the submap after this many frames")
    max_surface_views: float | None = Field(
        None,
        gt=1.0,
        description=(
            "close the submap once the surface it covers (distinct cells of 4 x map_voxel_m) "
            "exceeds this multiple of the largest surface one of its frames saw. Consecutive "
            "submaps share about one view of surface, so this bounds the storage overlap factor "
            "near 1 + 1/max_surface_views however slowly the sensor moves, where a frame count "
            "stores a lingering camera's view again every max_frames frames. None: off"
        ),
    )
    min_range_m: float = Field(0.1, ge=0, description="points nearer to the sensor are dropped")
    max_range_m: float = Field(8.0, gt=0, description="points farther from the sensor are dropped")
    map_voxel_m: float = Field(
        0.02,
        gt=0,
        description="points of a submap are averaged on a grid of this size before encoding",
    )
    loop_voxel_m: float = Field(
        0.05, gt=0, description="grid size of the coarse submap cloud used for loop closure"
    )
    compact_every_points: int = Field(
        400_000,
        ge=1000,
        description="re-average the accumulated points once this many are buffered",
    )
    normal_neighbours: int = Field(
        12, ge=4, description="neighbours of the PCA normal fit (sources without normals)"
    )
    normal_radius_m: float | None = Field(
        None, description="ignore normal-fit neighbours farther than this (None: no limit)"
    )
    max_map_points: int | None = Field(
        None,
        ge=100,
        description="cap on the points a submap encodes (seeded random subset; None: no cap)",
    )
    keep_points: bool = Field(
        False,
        description="keep each submap's points after encoding (for re-encoding experiments)",
    )
    keep_keyframe_images: bool = Field(
        True, description="keep the anchor frame's RGB-D images (needed by RGB-D loop closure)"
    )


class RgbdLoopConfig(Strict):
    """RGB-D loop closure: pose proximity + ORB, PnP-RANSAC, cv2.Odometry, dense ICP."""

    candidate_radius_m: float = Field(
        2.0, gt=0, description="reference anchors within this distance of the query are candidates"
    )
    max_candidates: int = Field(3, ge=1, description="best-matching candidates verified")
    orb_features: int = Field(1000, ge=100, description="ORB features per keyframe")
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
        0.03, gt=0, description="voxel size the submap clouds are thinned to for the refinement"
    )
    refine_max_points: int = Field(
        8000, ge=100, description="at most this many points per cloud in the refinement"
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
        0.01, gt=0, description="keyframe refinement: voxel size the keyframe clouds are thinned to"
    )
    keyframe_refine_max_points: int = Field(
        20000, ge=100, description="keyframe refinement: at most this many points per keyframe"
    )
    proximity_candidates: int = Field(
        2,
        ge=0,
        description="also try this many nearest older anchors (within candidate_radius_m) by "
        "dense refinement alone from their current relative estimate (0: ORB candidates only)",
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


class GravityConfig(Strict):
    """Up-direction factors from vertical structure (:mod:`slam.algorithm.gravity`): one per
    submap, measured on its anchor scan, on the anchor's tilt against a shared gravity
    direction. They remove the curved drift that loops cannot see (a constant pitch bias of the
    odometry). For sensors mounted within ``max_wall_tilt_rad`` of level in a world with walls
    (LiDAR on a vehicle); off for hand-held cameras."""

    enabled: bool = Field(False, description="add an up-direction factor per new submap")
    max_wall_tilt_rad: float = Field(
        0.25,
        gt=0,
        lt=1.5,
        description="a normal within this angle of horizontal (around the guessed up) counts "
        "as a wall in the first pass; later passes halve it three times",
    )
    min_wall_normals: int = Field(
        200, ge=10, description="fewer wall normals than this: no factor for that submap"
    )
    min_spread: float = Field(
        0.05,
        gt=0,
        le=1,
        description="a tilt axis whose normalised wall spread is below this gets no information "
        "(1 = walls facing every way; 0 = no wall constrains that axis)",
    )
    sigma_rad: float = Field(
        0.04,
        gt=0,
        description="standard deviation of one anchor scan's up direction where walls face "
        "every way. Looser than the 1-2 mrad measured on generated streets: the curved drift "
        "builds up over many submaps, so weak factors remove it, while tight ones pass each "
        "scan's error into the trajectory (0.003-0.04 tried; 0.04 has the best worst-variant "
        "vertical error, benchmarks/bench_variants.py)",
    )
    voxel_m: float = Field(0.25, gt=0, description="voxel size of the anchor scan's points")
    min_range_m: float = Field(2.0, ge=0, description="nearer points of the anchor scan: unused")
    max_range_m: float = Field(50.0, gt=0, description="farther points of the anchor scan: unused")
    normal_neighbours: int = Field(12, ge=5, description="neighbours of a normal's plane fit")
    normal_radius_m: float = Field(1.0, gt=0, description="neighbours farther than this: unused")


class PoseGraphConfig(Strict):
    """The GTSAM pose graph over submap anchors."""

    odometry_translation_sigma_m: float = Field(
        0.02, gt=0, description="odometry edge translation sigma, constant part"
    )
    odometry_translation_sigma_per_m: float = Field(
        0.02, ge=0, description="odometry edge translation sigma per metre travelled"
    )
    odometry_rotation_sigma_rad: float = Field(
        0.005, gt=0, description="odometry edge rotation sigma, constant part"
    )
    odometry_rotation_sigma_rad_per_m: float = Field(
        0.005, ge=0, description="odometry edge rotation sigma per metre travelled"
    )
    odometry_rotation_sigma_per_rad: float = Field(
        0.02, ge=0, description="odometry edge rotation sigma per radian turned"
    )
    loop_translation_sigma_m: float = Field(0.05, gt=0, description="loop edge translation sigma")
    loop_rotation_sigma_rad: float = Field(0.01, gt=0, description="loop edge rotation sigma")
    use_edge_covariances: bool = Field(
        True,
        description="odometry and loop edges that come with a covariance from their "
        "registration use it (plus the floors below) instead of the configured sigmas",
    )
    odometry_min_sigma_m: float = Field(
        0.002,
        ge=0,
        description="translation sigma added (in quadrature) to an odometry covariance",
    )
    odometry_min_sigma_rad: float = Field(
        0.001,
        ge=0,
        description="rotation sigma added (in quadrature) to an odometry covariance",
    )
    loop_min_sigma_m: float = Field(
        0.005,
        ge=0,
        description="translation sigma added (in quadrature) to a registration covariance",
    )
    loop_min_sigma_rad: float = Field(
        0.002, ge=0, description="rotation sigma added (in quadrature) to a registration covariance"
    )
    loop_kernel: Literal["cauchy", "none"] = Field(
        "cauchy", description="robust kernel of loop edges"
    )
    cauchy_k: float = Field(
        1.0, gt=0, description="Cauchy kernel scale in units of the whitened loop residual"
    )
    isam2_relinearize_threshold: float = Field(
        0.01, gt=0, description="iSAM2 relinearisation threshold"
    )
    online_gnc: bool = Field(
        True,
        description="solve the whole graph by GNC at every loop event and re-seed iSAM2 with "
        "the inlier loops (otherwise: iSAM2 with the Cauchy kernel only)",
    )
    isam2_extra_iterations: int = Field(
        5, ge=0, description="extra iSAM2 updates after a loop edge (converges the robust kernel)"
    )
    final_optimizer: Literal["lm", "gnc", "none"] = Field(
        "gnc",
        description="final batch optimisation: Levenberg-Marquardt on the robust graph, "
        "GNC (truncated least squares, odometry known inliers), or none",
    )
    gnc_inlier_probability: float = Field(
        0.99, gt=0, lt=1, description="GNC inlier threshold as a chi-square probability"
    )
    batch_max_iterations: int = Field(100, ge=1, description="Levenberg-Marquardt iterations")
    gravity: GravityConfig = Field(
        default_factory=GravityConfig, description="up-direction factors from vertical structure"
    )


class RemapConfig(Strict):
    """Remapping of submaps whose anchor moved after an optimisation."""

    enabled: bool = Field(True, description="move submaps in the neural map after optimisation")
    translation_threshold_m: float = Field(
        0.005, ge=0, description="remap a submap whose anchor moved more than this"
    )
    rotation_threshold_deg: float = Field(
        0.25, ge=0, description="remap a submap whose anchor turned more than this"
    )


class PipelineConfig(Strict):
    """What :class:`~slam.algorithm.pipeline.SlamPipeline` runs with (the application's run
    configuration holds the same sections at its top level)."""

    submaps: SubmapConfig = Field(default_factory=SubmapConfig, description="keyframing")
    loop_closure: LoopClosureConfig = Field(
        default_factory=LoopClosureConfig, description="loop detection and verification"
    )
    pose_graph: PoseGraphConfig = Field(default_factory=PoseGraphConfig, description="pose graph")
    remap: RemapConfig = Field(default_factory=RemapConfig, description="remapping")
    map_worker: bool = Field(
        True,
        description="run keyframing, normals, loop detection and the pose graph on one worker "
        "thread and encoding, fusion and remapping on another while the caller runs the "
        "odometry; results do not depend on it (each worker applies its jobs in submission "
        "order)",
    )
