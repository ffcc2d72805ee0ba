"""Options of the OpenCV RGB-D odometry front-end (:mod:`frontends.odometry.rgbd`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class RgbdOdometryConfig(BaseModel):
    """Options of the OpenCV RGB-D odometry front-end."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    odometry_type: Literal["rgbd", "depth", "rgb"] = Field(
        "rgbd",
        description="Terms used: 'rgbd' (photometric + ICP), 'depth' (ICP only), 'rgb' "
        "(photometric only).",
    )
    algorithm: Literal["common", "fast"] = Field(
        "common", description="OpenCV's OdometryAlgoType: 'common' (accurate) or 'fast'."
    )
    min_depth_m: float = Field(0.0, ge=0, description="Depth below this is ignored.")
    max_depth_m: float = Field(4.0, gt=0, description="Depth beyond this is ignored.")
    max_depth_diff_m: float = Field(
        0.07, gt=0, description="Largest depth difference of an ICP correspondence."
    )
    max_points_part: float = Field(
        0.07, gt=0, le=1, description="Fraction of pixels used by the photometric term."
    )
    iter_counts: list[int] = Field(
        default_factory=lambda: [7, 7, 7, 10],
        min_length=1,
        description="Iterations per pyramid level, finest level first.",
    )
    min_gradient_magnitudes: list[float] = Field(
        default_factory=lambda: [10.0, 10.0, 10.0, 10.0],
        min_length=1,
        description="Per-level image-gradient threshold of photometric pixels (same length as "
        "iter_counts).",
    )
    max_translation_m: float = Field(
        0.15, gt=0, description="A registration that moves further than this counts as failed."
    )
    max_rotation_deg: float = Field(
        15.0, gt=0, description="A registration that rotates more than this counts as failed."
    )
    downscale: int | None = Field(
        None,
        ge=1,
        le=8,
        description="Shrink images by this integer factor before registration; None picks "
        "round(width / 320), i.e. 2 at 640x480 (~3x faster than 1 there with the same drift on "
        "7-Scenes; at 320x240 shrinking further doubled the drift on the generated room).",
    )
    keyframe_translation_m: float = Field(
        0.03,
        ge=0,
        description="Replace the keyframe once the camera is this far from it (0: register "
        "frame to frame).",
    )
    keyframe_rotation_deg: float = Field(
        2.0, ge=0, description="Replace the keyframe once the camera has turned this much."
    )
    covariance_points: int = Field(
        2000,
        ge=0,
        le=10_000_000,
        description="Points of each frame used to evaluate the registration's point-to-plane "
        "Hessian (its covariance); 0 turns the covariance off.; at most 10,000,000",
    )
    covariance_max_distance_m: float = Field(
        0.05, gt=0, description="Correspondence gate of that evaluation."
    )
    covariance_factor: float = Field(
        20.0,
        gt=0,
        description="Covariance of a registration = this factor * sigma^2 H^-1 (sigma: its "
        "point-to-plane RMSE). Inflates the raw estimate for correlated residuals and the "
        "photometric term it does not model.",
    )
