"""LiDAR odometry with KISS-ICP (Vizzo et al., RA-L 2023), wrapped behind :class:`Odometry`."""

from __future__ import annotations

import logging

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from frontends.errors import DatasetError
from frontends.frame import Frame, point_ranges_m
from frontends.odometry.base import Odometry, OdometryResult, register_odometry

logger = logging.getLogger(__name__)


class KissIcpConfig(BaseModel):
    """Options of the KISS-ICP front-end (defaults are KISS-ICP's own)."""

    model_config = ConfigDict(extra="forbid")

    max_range_m: float = Field(100.0, gt=0, description="Points farther than this are dropped.")
    min_range_m: float = Field(
        0.0, ge=0, description="Points closer than this are dropped (e.g. the ego vehicle)."
    )
    voxel_size_m: float | None = Field(
        None,
        gt=0,
        description="Local-map voxel size; None uses max_range_m / 100 as KISS-ICP does.",
    )
    max_points_per_voxel: int = Field(20, ge=1, description="Points kept per local-map voxel.")
    deskew: bool = Field(
        True,
        description="Motion-compensate scans with constant velocity; only applies to frames "
        "that carry per-point times (Frame.point_times).",
    )
    initial_threshold_m: float = Field(
        2.0, gt=0, description="Initial correspondence threshold of the adaptive threshold."
    )
    min_motion_m: float = Field(
        0.1, ge=0, description="Motion below this does not update the adaptive threshold."
    )
    fixed_threshold_m: float | None = Field(
        None, gt=0, description="Use this correspondence threshold instead of the adaptive one."
    )
    max_num_iterations: int = Field(500, ge=1, description="ICP iterations per scan at most.")
    convergence_criterion: float = Field(
        1e-4, gt=0, description="ICP stops when the update norm falls below this."
    )
    max_num_threads: int = Field(0, ge=0, description="Threads for KISS-ICP (0 = all cores).")

    def to_kiss(self):
        """The equivalent ``kiss_icp.config.KISSConfig``."""
        from kiss_icp.config import KISSConfig

        config = KISSConfig()
        config.data.max_range = self.max_range_m
        config.data.min_range = self.min_range_m
        config.data.deskew = self.deskew
        config.mapping.voxel_size = (
            self.voxel_size_m if self.voxel_size_m is not None else self.max_range_m / 100.0
        )
        config.mapping.max_points_per_voxel = self.max_points_per_voxel
        config.adaptive_threshold.initial_threshold = self.initial_threshold_m
        config.adaptive_threshold.min_motion_th = self.min_motion_m
        config.adaptive_threshold.fixed_threshold = self.fixed_threshold_m
        config.registration.max_num_iterations = self.max_num_iterations
        config.registration.convergence_criterion = self.convergence_criterion
        config.registration.max_num_threads = self.max_num_threads
        return config


@register_odometry("kiss-icp")
class KissIcpOdometry(Odometry):
    """KISS-ICP scan-to-local-map registration. W is the frame of the first scan.

    Construct with a :class:`KissIcpConfig` or its fields as keyword arguments, e.g.
    ``KissIcpOdometry(max_range_m=80.0)``. Each result's ``points`` are the deskewed,
    range-filtered scan (sensor frame); after each :meth:`register`, ``last_keypoints`` holds the
    downsampled points that were registered.
    """

    def __init__(self, config: KissIcpConfig | None = None, **options) -> None:
        if config is not None and options:
            raise TypeError("pass either a KissIcpConfig or keyword options, not both")
        self.config = config if config is not None else KissIcpConfig(**options)
        if self.config.max_range_m <= self.config.min_range_m:
            raise ValueError(
                f"KissIcpConfig: max_range_m={self.config.max_range_m} must exceed "
                f"min_range_m={self.config.min_range_m}"
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
        ranges = point_ranges_m(points)
        usable = np.count_nonzero(
            (ranges > self.config.min_range_m) & (ranges < self.config.max_range_m)
        )
        if usable == 0:
            raise DatasetError(
                f"frame {frame.index}: empty scan ({len(points)} points, none within "
                f"{self.config.min_range_m}-{self.config.max_range_m} m); check the scan file "
                f"or the range limits"
            )
        if frame.point_times is not None and self.config.deskew:
            times = np.asarray(frame.point_times, dtype=np.float64).reshape(-1)
            if len(times) != len(points):
                raise DatasetError(
                    f"frame {frame.index}: {len(times)} point times for {len(points)} points; "
                    "check the source"
                )
        else:
            times = np.zeros(0)
        deskewed, keypoints = self._kiss.register_frame(points, times)
        deskewed = np.asarray(deskewed)
        self.last_keypoints = np.asarray(keypoints)
        return OdometryResult(
            np.array(self._kiss.last_pose, dtype=np.float64),
            points=deskewed if len(deskewed) > 0 else None,
        )
