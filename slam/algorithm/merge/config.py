"""Settings of a multi-session merge (:mod:`slam.algorithm.merge.merge`)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from common.config import Strict


class MergeConfig(BaseModel):
    """Inter-session loop search, verification on decoded surfaces, and the joint graph."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    ratio_test: float = Field(0.8, gt=0, le=1, description="Lowe ratio of descriptor matches")
    min_descriptor_inliers: int = Field(
        12, ge=3, description="RANSAC inliers of the descriptor match for a candidate"
    )
    descriptor_inlier_vu: float = Field(
        1.0, gt=0, description="RANSAC inlier distance of keypoint positions, voxel units"
    )
    max_fits_per_submap: int = Field(
        8,
        ge=1,
        le=1000,
        description="earlier submaps with the most ratio-test matches given a RANSAC fit, per "
        "query submap; at most 1000",
    )
    max_candidates_per_submap: int = Field(
        3,
        ge=1,
        le=1000,
        description="descriptor matches per query submap tried, best first, until one verifies; "
        "at most 1000",
    )
    surface_max_points: int = Field(
        20000,
        ge=100,
        le=10_000_000,
        description="decoded surface points kept per submap for verification; at most 10,000,000",
    )
    surface_subdivisions: int = Field(
        2,
        ge=1,
        le=16,
        description="lattice cells per voxel edge when decoding a submap's surface (1 to 16)",
    )
    icp_gates_vu: tuple[float, ...] = Field(
        (3.0, 1.5, 0.75, 0.4, 0.25),
        description="point-to-plane ICP correspondence gates, voxel units (the last sets the "
        "pose's accuracy)",
    )
    icp_tolerance_vu: float = Field(
        1e-3,
        gt=0,
        le=0.1,
        description="an ICP gate ends once its update is below this, voxel units (its rotation "
        "in rad counts alike); at most 0.1. At 1e-3 a registration of a LiDAR submap to the "
        "stored map takes half the iterations of 1e-5 and moves by under 1 mm",
    )
    overlap_gate_vu: float = Field(
        0.75,
        gt=0,
        description="after ICP, a query surface point within this distance of the reference "
        "surface counts as overlapping (inlier fraction, residual), voxel units",
    )
    min_inlier_fraction: float = Field(
        0.4, ge=0, le=1, description="overlapping query surface points (overlap_gate_vu) after ICP"
    )
    max_residual_vu: float = Field(
        0.25,
        gt=0,
        description="robust point-to-plane residual sigma of the overlapping points allowed, "
        "voxel units",
    )
    min_eigenvalue: float = Field(
        0.01, ge=0, description="smallest normalised ICP Hessian eigenvalue (not degenerate)"
    )
    max_correction_vu: float = Field(
        3.0, gt=0, description="ICP may move the descriptor's guess at most this far, voxel units"
    )
    max_correction_deg: float = Field(
        10.0, gt=0, description="ICP may rotate the descriptor's guess at most this much"
    )
    covariance_factor: float = Field(
        1.0, gt=0, description="scale of the ICP covariance of an inter-session edge"
    )
    loop_min_sigma_m: float = Field(
        0.01, ge=0, description="translation sigma floor of an inter-session edge"
    )
    loop_min_sigma_rad: float = Field(
        0.002, ge=0, description="rotation sigma floor of an inter-session edge"
    )
    gnc_inlier_probability: float = Field(
        0.99, gt=0, lt=1, description="GNC inlier threshold of the joint graph (chi-square)"
    )
    remap_translation_m: float = Field(
        0.005, ge=0, description="a submap whose merged anchor moved less stays where it was"
    )
    remap_rotation_deg: float = Field(
        0.05, ge=0, description="a submap whose merged anchor turned less stays where it was"
    )


class LocaliseConfig(Strict):
    """Continuous localisation in a stored map (``slam.run --map``,
    :mod:`slam.algorithm.merge.map_constraints`): after the first placement, every closed live
    submap is registered to the stored submaps near its estimate and constrains its anchor in
    the map's frame. Registration and its gates are the merge's (:class:`MergeConfig`)."""

    continuous: bool = Field(
        True,
        description="register every closed submap after the first placement to the stored map "
        "and add each verified registration to the pose graph as a prior on that anchor in the "
        "map's frame; false: only the first placement (and the run's own loops) hold the run",
    )
    gravity_while_anchored: bool = Field(
        False,
        description="with continuous: measure the gravity direction at each new anchor also "
        "while the run is anchored in the stored map (the last closed submap's registration "
        "held), whose priors hold the attitude already; false saves the scan's normal fit, "
        "about 20 ms a LiDAR submap, and a run that leaves the map measures it again",
    )
    placement_prior_sigma_m: float = Field(
        10.0,
        gt=0,
        le=1e6,
        description="with continuous: the first anchor's prior once the session is placed, "
        "loose, so that the registrations to the map place the session together rather than "
        "the first one alone (translation sigma, m; at most 1e6)",
    )
    placement_prior_sigma_rad: float = Field(
        0.5, gt=0, le=3.2, description="... and its rotation sigma (rad; at most 3.2)"
    )
    max_map_submaps: int = Field(
        3,
        ge=1,
        le=100,
        description="stored submaps nearest the live submap (surface centres in the map's "
        "frame) whose decoded surfaces form the reference of one registration; at most 100",
    )
    near_factor: float = Field(
        1.0,
        gt=0,
        le=100,
        description="a stored submap is near when its surface centre lies within this factor "
        "times the sum of the two submaps' RMS radii of the live submap's estimated centre; at "
        "most 100",
    )
    min_inlier_fraction: float = Field(
        0.7,
        ge=0,
        le=1,
        description="a registration after the placement constrains its anchor only when at "
        "least this fraction of the live submap's points lies on the stored surface (the "
        "merge's overlap gate, stricter): a submap that sees the stored surface only in part "
        "converges where the unmatched part pulls it (measured on 7-Scenes redkitchen: 0.72 and "
        "above within 1.4 cm of the truth, 0.64 and below 7 to 16 cm off while the registration "
        "claimed 1 cm); 0 to 1",
    )
    max_query_points: int = Field(
        2500,
        ge=100,
        le=10_000_000,
        description="live submap points registered per submap (a random subset beyond it; the "
        "registration's cost grows with it: 2,500 instead of 5,000 halves it and moved the "
        "registered poses by 0.4-1 cm, the localised error not at all); at most 10,000,000",
    )
    coarse_query_points: int = Field(
        625,
        ge=0,
        le=10_000_000,
        description="of those, the points the registration's ICP gates wider than half a voxel "
        "align (a random subset; the finer gates align them all): the coarse gates only bring "
        "the pose into the fine ones' reach (measured on the generated street: a quarter of "
        "the points there cut the registrations' CPU by a third and moved the registered poses "
        "by at most 2.5 mm, the kitchen's by 0.5 mm); the ambiguity search's score profile "
        "counts them alone too; 0: all; at most 10,000,000",
    )
    graph_consistency_probability: float = Field(
        0.9999,
        ge=0,
        lt=1,
        description="reject a registration outside this chi-square quantile (6 dof) of the "
        "graph's marginal covariance of the anchor plus the registration's own, as for a LiDAR "
        "loop; 0: off",
    )
    ambiguity_check: bool = Field(
        True,
        description="re-register from the best other peaks of the inlier score along the "
        "reference's main axis and the weakest Hessian direction, and reject when one converges "
        "elsewhere and scores about as well (slam/algorithm/loops/ambiguity.py)",
    )
    ambiguity_step_vu: float = Field(
        1.0, gt=0, le=100, description="grid step of the score profile, voxel units; at most 100"
    )
    ambiguity_max_offset_vu: float = Field(
        20.0,
        gt=0,
        le=1000,
        description="the profile reaches this far (or the reference's RMS radius when smaller), "
        "voxel units; at most 1000",
    )
    ambiguity_min_separation_vu: float = Field(
        2.0,
        gt=0,
        le=1000,
        description="an alternative lies at least this far from the chosen one, voxel units; at "
        "most 1000",
    )
    ambiguity_min_separation_deg: float = Field(
        2.0, gt=0, le=180, description="... or is rotated at least this much from it (deg)"
    )
    ambiguity_max_realignments: int = Field(
        2, ge=1, le=100, description="profile peaks re-registered per registration; at most 100"
    )
    ambiguity_score_ratio: float = Field(
        0.9,
        gt=0,
        le=1,
        description="ambiguous when an alternative scores at least this fraction of the chosen "
        "solution's inlier score (at most 1)",
    )
