"""Configuration of the pose graph and its up-direction (gravity) factors."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from common.config import Strict


class GravityConfig(Strict):
    """Up-direction factors from vertical structure (:mod:`slam.algorithm.graph.gravity`): one per
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
    voxel_m: float = Field(
        0.25, ge=0.01, description="voxel size of the anchor scan's points (at least 1 cm)"
    )
    min_range_m: float = Field(2.0, ge=0, description="nearer points of the anchor scan: unused")
    max_range_m: float = Field(50.0, gt=0, description="farther points of the anchor scan: unused")
    normal_neighbours: int = Field(
        12, ge=5, le=256, description="neighbours of a normal's plane fit; at most 256"
    )
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
    frames_follow_next_anchor: bool = Field(
        True,
        description="a frame's pose also follows the next submap's anchor, in proportion to the "
        "path travelled from its own (the odometry's drift between two anchors is spread over the "
        "frames in between), except in submaps registered to a stored map, whose registration "
        "fits their frames rigidly; off: every frame rigid on its own anchor, as the map fuses it",
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
        5,
        ge=0,
        le=1000,
        description="extra iSAM2 updates after a loop edge (converges the robust kernel); at most "
        "1000",
    )
    final_optimizer: Literal["lm", "gnc", "none"] = Field(
        "gnc",
        description="final batch optimisation: Levenberg-Marquardt on the robust graph, "
        "GNC (truncated least squares, odometry known inliers), or none",
    )
    gnc_inlier_probability: float = Field(
        0.99, gt=0, lt=1, description="GNC inlier threshold as a chi-square probability"
    )
    batch_max_iterations: int = Field(
        100, ge=1, le=10_000, description="Levenberg-Marquardt iterations; at most 10,000"
    )
    gravity: GravityConfig = Field(
        default_factory=GravityConfig, description="up-direction factors from vertical structure"
    )
