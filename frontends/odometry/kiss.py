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
from kiss_icp.voxelization import voxel_down_sample
from pydantic import BaseModel, ConfigDict, Field, model_validator

from common.normals import estimate_normals
from common.point_to_plane import point_to_plane_icp
from frontends.errors import DatasetError
from frontends.frame import Frame, point_ranges_m
from frontends.odometry.base import Odometry, OdometryResult, register_odometry

logger = logging.getLogger(__name__)


_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)


class KissDataConfig(DataConfig):
    """``kiss_icp``'s ``data`` section; unknown keys are rejected."""

    model_config = _STRICT


class KissMappingConfig(MappingConfig):
    """``kiss_icp``'s ``mapping`` section; unknown keys are rejected, sizes bounded."""

    model_config = _STRICT

    voxel_size: float | None = Field(
        None, ge=0.001, description="local map voxel (m; None: max_range / 100); at least 1 mm"
    )
    max_points_per_voxel: int = Field(
        20, ge=1, le=10_000, description="points kept per local map voxel (1 to 10,000)"
    )


class KissRegistrationConfig(RegistrationConfig):
    """``kiss_icp``'s ``registration`` section; unknown keys are rejected, sizes bounded."""

    model_config = _STRICT

    max_num_iterations: int | None = Field(
        500, ge=1, le=10_000, description="ICP iterations per scan (1 to 10,000)"
    )
    max_num_threads: int | None = Field(
        0, ge=0, le=1024, description="ICP threads (0: all cores; at most 1024)"
    )


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
    on, else None (the frame's own points).

    ``start_scans``: KISS-ICP predicts each scan's pose by constant velocity, starting from
    rest, and its point-to-point registration against a local map of one or two scans is pulled
    towards zero motion by the ground rings, which move with the sensor. A sequence that starts
    moving along blank walls then never recovers its first metres: on the generated sparse
    street KISS-ICP put the first 9 scans 0.7 m apart instead of 6.9 m, an error the whole
    trajectory kept. So the first ``start_scans`` scans after the first are registered to their
    predecessor by point-to-plane ICP (:meth:`start_motion`, where the ground does not bias
    along-track motion) and enter KISS-ICP's local map, velocity and threshold at that pose;
    KISS-ICP takes over from there (or earlier, for a scan where that ICP does not hold).
    """

    def __init__(
        self, config: KissIcpConfig | None = None, start_scans: int = 0, **options
    ) -> None:
        if config is not None and options:
            raise TypeError("pass either a KissIcpConfig or keyword options, not both")
        self.config = config if config is not None else KissIcpConfig(**options)
        self.start_scans = start_scans
        self._previous_scan: np.ndarray | None = None  # kept while start_scans last
        self._num_registered = 0
        data = self.config.data
        if data.max_range <= data.min_range:
            raise ValueError(
                f"KissIcpConfig: data.max_range={data.max_range} must exceed "
                f"data.min_range={data.min_range}"
            )
        from kiss_icp.kiss_icp import KissICP

        self._kiss = KissICP(self.config.to_kiss())

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
        registered = None
        if self._previous_scan is not None:
            registered = self._register_start(points, times)
        kept, _ = registered or self._kiss.register_frame(points, times)
        # KISS-ICP returns an empty scan for a frame without points in its range (and leaves its
        # pose at the prediction): checked after the fact, which spares a pass over the points
        if len(kept) == 0:
            raise DatasetError(
                f"frame {frame.index}: empty scan ({len(points)} points, none within "
                f"{self.config.data.min_range}-{self.config.data.max_range} m); check the scan "
                "file or the range limits"
            )
        self._num_registered += 1
        starting = self._num_registered == 1 or registered is not None
        keep = starting and self._num_registered <= self.start_scans
        self._previous_scan = kept if keep else None
        # without per-point times nothing was corrected: the map takes the frame's own points
        # (and applies its own range limits, submaps.min_range_m / max_range_m)
        return OdometryResult(
            np.array(self._kiss.last_pose, dtype=np.float64),
            points=np.asarray(kept) if len(times) else None,
        )

    def _register_start(self, points: np.ndarray, times: np.ndarray):
        """KISS-ICP's ``register_frame`` with the pose from :meth:`start_motion`; None when that
        does not hold (the caller lets KISS-ICP register the scan)."""
        kiss = self._kiss
        frame = kiss.preprocessor.preprocess(points, times, kiss.last_delta)
        T_previous_scan = self.start_motion(self._previous_scan, frame)
        if T_previous_scan is None:
            return None
        source, frame_downsample = kiss.voxelize(frame)
        new_pose = kiss.last_pose @ T_previous_scan
        prediction = kiss.last_pose @ kiss.last_delta
        kiss.adaptive_threshold.update_model_deviation(np.linalg.inv(prediction) @ new_pose)
        kiss.local_map.update(frame_downsample, new_pose)
        kiss.last_delta = T_previous_scan
        kiss.last_pose = new_pose
        return frame, source

    def start_motion(self, previous: np.ndarray, scan: np.ndarray) -> np.ndarray | None:
        """``T_previous_scan`` by point-to-plane ICP from rest, or None when it does not hold.

        Both scans are range-filtered as KISS-ICP does and thinned to one point per half local-map
        voxel; normals by PCA on ``previous``. The motion holds when ICP converged with at least
        half of the scan's points on the previous scan's surfaces.
        """
        data, voxel_m = self.config.data, 0.5 * self.voxel_size_m

        def thinned(points: np.ndarray) -> np.ndarray:
            ranges = point_ranges_m(points)
            return voxel_down_sample(
                points[(ranges >= data.min_range) & (ranges <= data.max_range)], voxel_m
            )

        reference, query = thinned(np.asarray(previous)), thinned(np.asarray(scan))
        normals, valid = estimate_normals(
            reference, np.zeros(3), num_neighbours=10, max_radius_m=4 * voxel_m
        )
        result = point_to_plane_icp(
            reference[valid],
            normals[valid],
            query,
            np.eye(4),
            max_distances_m=(4 * voxel_m, 2 * voxel_m, voxel_m),
            max_iterations=30,
        )
        T = result.T_ref_query
        if result.converged and result.inlier_fraction >= 0.5 and np.all(np.isfinite(T)):
            return T
        logger.debug("start motion does not hold (inliers %.2f)", result.inlier_fraction)
        return None
