"""Settings of keyframing (:mod:`slam.algorithm.submaps`): when a submap closes and how its
points are kept."""

from __future__ import annotations

from pydantic import Field

from common.config import Strict


class SubmapConfig(Strict):
    """Keyframing: when a submap closes and how its points are kept."""

    max_distance_m: float = Field(
        2.0, gt=0, description="close the submap when the sensor is this far from the anchor"
    )
    max_rotation_deg: float = Field(
        30.0, gt=0, description="close the submap when the sensor turned this much from the anchor"
    )
    max_frames: int = Field(
        30, ge=1, le=100_000, description="close the submap after this many frames; at most 100,000"
    )
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
    loop_max_range_m: float | None = Field(
        None,
        gt=0,
        description="points farther from the sensor than this are left out of the loop-closure "
        "cloud but still mapped (None: max_range_m), so that the map can reach farther than "
        "what loop closure was tuned on",
    )
    far_map_voxel_m: float | None = Field(
        None,
        ge=0.001,
        description="points beyond loop_max_range_m are averaged on a grid of this size (None: "
        "map_voxel_m): far returns are sparse, and fewer of them cost less to encode",
    )
    map_voxel_m: float = Field(
        0.02,
        ge=0.001,
        description="points of a submap are averaged on a grid of this size before encoding (at "
        "least 1 mm)",
    )
    loop_voxel_m: float = Field(
        0.05,
        ge=0.001,
        description="grid size of the coarse submap cloud used for loop closure (at least 1 mm)",
    )
    compact_every_points: int = Field(
        400_000,
        ge=1000,
        le=100_000_000,
        description="re-average the accumulated points once this many are buffered; at most "
        "100,000,000",
    )
    normal_neighbours: int = Field(
        12,
        ge=4,
        le=256,
        description="neighbours of the PCA normal fit (sources without normals); at most 256",
    )
    normal_radius_m: float | None = Field(
        None, description="ignore normal-fit neighbours farther than this (None: no limit)"
    )
    max_map_points: int | None = Field(
        None,
        ge=100,
        le=100_000_000,
        description="cap on the points a submap encodes (seeded random subset; None: no cap); at "
        "most 100,000,000",
    )
    localise_voxel_m: float | None = Field(
        None,
        ge=0.001,
        description="grid a localisation-only run's submap points are kept on, one a voxel "
        "(near and far alike; at least 1 mm): they are never encoded, only registered to the "
        "stored map (a few thousand of them) and matched by loop closure, so a grid finer than "
        "the loop cloud's only costs (measured on 7-Scenes redkitchen: 0.05 instead of 0.025 m "
        "cut a frame's keyframing from 14 to 4 ms; on the generated street 0.5 instead of "
        "0.35 m saved little and cost 1.3 cm of worst error). None: map_voxel_m",
    )
    localise_scan_spacing_m: float | None = Field(
        None,
        gt=0,
        description="once a localisation-only run is placed in the stored map, it adds a "
        "frame's points to its submap only once the sensor has moved this far, or turned "
        "localise_scan_turn_deg, since the last frame it added (the submap's first frame "
        "always): the submap is registered as a few thousand points and matched by loop "
        "closure on a coarse grid, so nearly coincident scans only cost keyframing time. Until "
        "placed, every frame (a submap is then matched against the whole map, and sparser "
        "submaps were placed wrongly). None: every frame",
    )
    localise_scan_turn_deg: float = Field(
        10.0, gt=0, description="see localise_scan_spacing_m (unused without it)"
    )
    keep_points: bool = Field(
        False,
        description="keep each submap's points after encoding (for re-encoding experiments)",
    )
    keep_keyframe_images: bool = Field(
        True, description="keep the anchor frame's RGB-D images (needed by RGB-D loop closure)"
    )
