"""LiDAR odometry with KISS-ICP (Vizzo et al., RA-L 2023), wrapped behind :class:`Odometry`."""

from __future__ import annotations

import logging

import numpy as np
from kiss_icp.config import KISSConfig
from kiss_icp.config.config import (
    AdaptiveThresholdConfig,
    DataConfig,
    MappingConfig,
    RegistrationConfig,
)
from pydantic import BaseModel, ConfigDict, Field, model_validator

from frontends.errors import DatasetError
from frontends.frame import Frame
from frontends.odometry.base import Odometry, OdometryResult, register_odometry

logger = logging.getLogger(__name__)


_STRICT = ConfigDict(extra="forbid")


class KissDataConfig(DataConfig):
    """``kiss_icp``'s ``data`` section; unknown keys are rejected."""

    model_config = _STRICT


class KissMappingConfig(MappingConfig):
    """``kiss_icp``'s ``mapping`` section; unknown keys are rejected."""

    model_config = _STRICT


class KissRegistrationConfig(RegistrationConfig):
    """``kiss_icp``'s ``registration`` section; unknown keys are rejected."""

    model_config = _STRICT


class KissAdaptiveThresholdConfig(AdaptiveThresholdConfig):
    """``kiss_icp``'s ``adaptive_threshold`` section; unknown keys are rejected."""

    model_config = _STRICT


class KissIcpConfig(BaseModel):
    """KISS-ICP's own configuration (``kiss_icp.config.KISSConfig`` without ``out_dir``), with
    unknown keys rejected. Fields, units (metres) and defaults are KISS-ICP's
    (``kiss_icp/config/config.py``); ``mapping.voxel_size`` None means ``data.max_range / 100``
    as KISS-ICP does, and ``data.deskew`` applies only to frames that carry per-point times
    (``Frame.point_times``)."""

    model_config = _STRICT

    data: KissDataConfig = Field(
        default_factory=KissDataConfig,
        description="max_range / min_range: points outside are dropped; deskew: motion-compensate",
    )
    mapping: KissMappingConfig = Field(
        default_factory=KissMappingConfig,
        description="voxel_size of the local map (None: max_range / 100); max_points_per_voxel",
    )
    registration: KissRegistrationConfig = Field(
        default_factory=KissRegistrationConfig,
        description="ICP max_num_iterations, convergence_criterion, max_num_threads (0 = all)",
    )
    adaptive_threshold: KissAdaptiveThresholdConfig = Field(
        default_factory=KissAdaptiveThresholdConfig,
        description="correspondence threshold: initial_threshold, min_motion_th, or a "
        "fixed_threshold instead of the adaptive one",
    )

    @model_validator(mode="after")
    def _positive(self) -> KissIcpConfig:
        if self.data.min_range < 0 or (self.mapping.voxel_size or 1.0) <= 0:
            raise ValueError("data.min_range must be >= 0 and mapping.voxel_size > 0")
        return self

    def to_kiss(self) -> KISSConfig:
        """The equivalent ``kiss_icp.config.KISSConfig`` with the voxel size resolved."""
        config = KISSConfig(**self.model_dump())
        if config.mapping.voxel_size is None:
            config.mapping.voxel_size = config.data.max_range / 100.0
        return config


@register_odometry("kiss-icp")
class KissIcpOdometry(Odometry):
    """KISS-ICP scan-to-local-map registration. W is the frame of the first scan.

    Construct with a :class:`KissIcpConfig` or its sections as keyword arguments, e.g.
    ``KissIcpOdometry(data={"max_range": 80.0})``. A result's ``points`` are the deskewed,
    range-filtered scan (sensor frame) when the frame has per-point times and ``data.deskew`` is
    on, else None (the frame's own points); after each :meth:`register`, ``last_keypoints`` holds
    the downsampled points that were registered.
    """

    def __init__(self, config: KissIcpConfig | None = None, **options) -> None:
        if config is not None and options:
            raise TypeError("pass either a KissIcpConfig or keyword options, not both")
        self.config = config if config is not None else KissIcpConfig(**options)
        data = self.config.data
        if data.max_range <= data.min_range:
            raise ValueError(
                f"KissIcpConfig: data.max_range={data.max_range} must exceed "
                f"data.min_range={data.min_range}"
            )
        from kiss_icp.kiss_icp import KissICP

        self._kiss = KissICP(self.config.to_kiss())
        self.last_keypoints: np.ndarray = np.zeros((0, 3))

    @property
    def voxel_size_m(self) -> float:
        """Local-map voxel size in use."""
        return float(self._kiss.config.mapping.voxel_size)

    def register(self, frame: Frame) -> OdometryResult:
        points = np.asarray(frame.points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise DatasetError(
                f"frame {frame.index}: points must be (N, 3), got {points.shape}; check the source"
            )
        if frame.point_times is not None and self.config.data.deskew:
            times = np.asarray(frame.point_times, dtype=np.float64).reshape(-1)
            if len(times) != len(points):
                raise DatasetError(
                    f"frame {frame.index}: {len(times)} point times for {len(points)} points; "
                    "check the source"
                )
        else:
            times = np.zeros(0)
        # KISS-ICP returns an empty scan for a frame without points in its range (and leaves its
        # pose at the prediction): checked after the fact, which spares a pass over the points
        kept, keypoints = self._kiss.register_frame(points, times)
        if len(kept) == 0:
            raise DatasetError(
                f"frame {frame.index}: empty scan ({len(points)} points, none within "
                f"{self.config.data.min_range}-{self.config.data.max_range} m); check the scan "
                "file or the range limits"
            )
        self.last_keypoints = np.asarray(keypoints)
        # without per-point times nothing was corrected: the map takes the frame's own points
        # (and applies its own range limits, submaps.min_range_m / max_range_m)
        return OdometryResult(
            np.array(self._kiss.last_pose, dtype=np.float64),
            points=np.asarray(kept) if len(times) else None,
        )
