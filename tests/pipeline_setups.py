"""Pipeline set-ups shared by the pipeline, recorder and determinism tests: the generated room
and street, their run configurations, and a drifting odometry that gives loop closure a known
drift to remove."""

from __future__ import annotations

import numpy as np

from frontends.frame import Frame
from frontends.odometry.base import Odometry, OdometryResult
from frontends.odometry.ground_truth import GroundTruthOdometry
from slam.algorithm.loops.base import LoopCandidate, LoopDetector
from slam.algorithm.pipeline import SlamPipeline
from slam.algorithm.submaps import SubmapRecord
from slam.assembly.builders import build_map
from slam.assembly.config import RunConfig

ROOM = {"kind": "rgbd", "num_frames": 240, "seed": 0, "width": 320, "height": 240}
STREET = {"kind": "lidar", "num_frames": 150, "seed": 0, "azimuth_steps": 1024}


class DriftingOdometry(Odometry):
    """Ground-truth increments with a constant yaw bias and a scale error per frame, and
    optionally a pitch bias (nose up about the sensor's y axis, for a z-up LiDAR)."""

    def __init__(
        self, yaw_deg_per_frame: float, scale: float, up_axis: int, pitch_deg_per_frame: float = 0.0
    ) -> None:
        self._gt = GroundTruthOdometry()
        self._previous: np.ndarray | None = None
        self._pose = np.eye(4)
        angle = np.radians(yaw_deg_per_frame)
        axes = [a for a in range(3) if a != up_axis]
        self._bias = np.eye(4)
        self._bias[axes[0], axes[0]] = self._bias[axes[1], axes[1]] = np.cos(angle)
        self._bias[axes[0], axes[1]] = -np.sin(angle)
        self._bias[axes[1], axes[0]] = np.sin(angle)
        pitch = np.radians(pitch_deg_per_frame)
        nose_up = np.eye(4)
        nose_up[0, 0] = nose_up[2, 2] = np.cos(pitch)
        nose_up[0, 2], nose_up[2, 0] = -np.sin(pitch), np.sin(pitch)
        self._bias = self._bias @ nose_up
        self._scale = scale

    def register(self, frame: Frame) -> OdometryResult:
        T = self._gt.register(frame).T_W_S
        if self._previous is not None:
            step = np.linalg.inv(self._previous) @ T
            step[:3, 3] *= self._scale
            self._pose = self._pose @ step @ self._bias
        self._previous = T
        return OdometryResult(self._pose.copy())


class FalseLoopInjector(LoopDetector):
    """Passes the real detector's candidates through and adds one wrong 'verified' edge."""

    def __init__(self, inner: LoopDetector, at_submap: int, wrong_by_m: float) -> None:
        super().__init__()
        self.descriptors = inner.descriptors
        self.inner = inner
        self.at_submap = at_submap
        self.wrong_by_m = wrong_by_m

    def process(self, submap: SubmapRecord, T_W_A_estimates, relative_covariance=None):
        candidates = self.inner.process(submap, T_W_A_estimates, relative_covariance)
        j = submap.submap_id
        if j == self.at_submap:
            T = np.linalg.inv(T_W_A_estimates[j - 4]) @ T_W_A_estimates[j]
            T[:3, 3] += [self.wrong_by_m, -self.wrong_by_m, 0.0]
            candidates.append(LoopCandidate(j - 4, j, True, "accepted", T, {}, "injected"))
        return candidates


def room_config(**submaps) -> RunConfig:
    return RunConfig.model_validate(
        {
            "source": {"dataset": "generated", "depth": {"stride": 2, "max_depth_m": 6.0}},
            "submaps": {
                "max_frames": 10,
                "max_distance_m": 0.5,
                "max_range_m": 6.0,
                "map_voxel_m": 0.03,
                "keep_points": True,
                **submaps,
            },
            "loop_closure": {"min_travel_m": 1.0, "rgbd": {"candidate_radius_m": 1.5}},
            # Remap every anchor that moved by more than 2 mm / 0.1 deg, so that the map holds
            # every submap at its final pose up to that.
            "remap": {"translation_threshold_m": 0.002, "rotation_threshold_deg": 0.1},
            # meshed on a 5 cm lattice: the tests compare two meshes made alike
            "mapping": {"voxel_size_m": 0.1, "device": "cpu", "mesh_subdivisions": 2},
            "viz": {"mode": "none", "mesh_every_submaps": 10**6, "mesh_after_remap": False},
        }
    )


def run(cfg: RunConfig, source, odometry: Odometry, detector=None) -> SlamPipeline:
    pipeline = SlamPipeline(
        cfg.pipeline_config(), source.sensor, odometry, build_map(cfg), loop_detector=detector
    )
    for frame in source:
        pipeline.process(frame)
    pipeline.finish()
    return pipeline


def room_odometry() -> DriftingOdometry:
    return DriftingOdometry(yaw_deg_per_frame=0.08, scale=1.01, up_axis=1)


def street_config(**top_level) -> RunConfig:
    """The generated street's LiDAR setup (15 m submaps, 0.5 m map voxels, proximity loops)."""
    return RunConfig.model_validate(
        {
            "submaps": {
                "max_distance_m": 15.0,
                "max_rotation_deg": 360.0,
                "max_frames": 1000,
                "max_range_m": 25.0,
                "map_voxel_m": 0.25,
                "loop_voxel_m": 0.5,
                "normal_radius_m": 1.0,
                "max_map_points": 3000,
            },
            "loop_closure": {"min_travel_m": 40.0, "lidar": {"proximity_radius_m": 25.0}},
            "pose_graph": {
                "odometry_translation_sigma_per_m": 0.01,
                "odometry_rotation_sigma_rad_per_m": 0.0005,
                "loop_translation_sigma_m": 0.1,
                "loop_rotation_sigma_rad": 0.005,
            },
            "mapping": {"voxel_size_m": 0.5, "min_points_per_voxel": 2, "device": "cpu"},
            "viz": {"mode": "none", "mesh_every_submaps": 10**6, "mesh_after_remap": False},
            **top_level,
        }
    )
