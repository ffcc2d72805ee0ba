"""A local TSDF model of the recent RGB-D frames for frame-to-model tracking (KinectFusion style).

:class:`LocalTsdfModel` wraps an OpenCV 5 ``cv2.Volume`` (dense TSDF): frames are integrated at
their tracked poses and the volume is ray-cast at a pose to get a depth image and normals that a
new frame is registered against with ``cv2.Odometry``. The model is *local*: a cube of
``resolution`` voxels placed around the camera, re-placed (and refilled with the last few frames)
when the camera leaves it or turns too far from the direction it was placed for.

Two quirks of OpenCV 5.0's CPU TSDF integration are worked around here (measured by integrating
one frame and ray-casting it from the same pose):

* The voxel loop along the volume's z axis advances its position before using it, so voxel ``z``
  receives the TSDF of position ``z + 1`` and surfaces are ray-cast one voxel off along that
  axis. Integrating from a camera shifted by one voxel along the volume's z axis stores every
  value where it belongs: median depth error -0.2 mm instead of +39 mm with 4 cm voxels on the
  rendered room of ``tests/test_odometry.py``, 0.5 mm instead of 18 mm with 2 cm voxels on a
  real 7-Scenes frame.
* That loop starts at the first voxel in front of the camera but counts positions from voxel 0,
  so a camera looking along the volume's +z axis from inside the volume garbles it (35 % of the
  pixels ray-cast with the camera 1 m inside). The volume is therefore oriented with its z axis
  pointing back at the camera (then the loop always starts at voxel 0), and re-placed before the
  view turns ``max_view_angle_deg`` away from that direction.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

# Volume axes in the camera frame at placement: x along x, y and z flipped (a proper rotation).
_FLIP = np.diag([1.0, -1.0, -1.0])


class LocalTsdfModelConfig(BaseModel):
    """The local TSDF model used by frame-to-model tracking."""

    model_config = ConfigDict(extra="forbid")

    voxel_size_m: float = Field(0.03, gt=0, description="TSDF voxel edge length.")
    resolution: int = Field(
        128,
        ge=16,
        le=512,
        description="Voxels per side of the cubic volume (side = resolution * voxel_size_m). "
        "Integration visits every voxel in front of the camera, so its cost grows with the cube.",
    )
    truncation_voxels: float = Field(3.0, gt=0, description="TSDF truncation distance, in voxels.")
    max_weight: int = Field(
        64, ge=1, description="Frames averaged per voxel at most (older ones fade out)."
    )
    camera_depth_fraction: float = Field(
        0.85,
        gt=0.5,
        lt=1,
        description="Where the camera sits along the volume's depth axis when it is placed "
        "(0.85: 15 % of the side behind the camera, 85 % in front).",
    )
    margin_voxels: int = Field(
        4, ge=1, description="Re-place the volume when the camera comes this close to a face."
    )
    max_view_angle_deg: float = Field(
        60.0,
        gt=0,
        lt=90,
        description="Re-place the volume when the viewing direction has turned this far from "
        "the one it was placed for (OpenCV 5.0's integration needs less than 90).",
    )
    keyframes_only: bool = Field(
        False,
        description="Integrate only the frames that become keyframes (one integration and one "
        "ray-cast per keyframe instead of an integration per frame).",
    )
    refill_frames: int = Field(
        8, ge=0, description="Recent frames integrated again into a re-placed volume."
    )
    min_valid_fraction: float = Field(
        0.3,
        ge=0,
        le=1,
        description="Track against the model only when its ray-cast covers at least this "
        "fraction of the frame's valid depth pixels.",
    )


class LocalTsdfModel:
    """A cube of TSDF voxels around the camera: integrate frames, ray-cast depth and normals.

    ``K`` is the 3x3 pinhole matrix of the (already downscaled) depth images, ``width`` x
    ``height`` their size. Poses are ``T_W_C`` (camera to world), depth is float32 metres with
    0 = invalid.
    """

    def __init__(
        self,
        config: LocalTsdfModelConfig,
        K: np.ndarray,
        width: int,
        height: int,
        max_depth_m: float,
    ) -> None:
        self.config = config
        self._K = np.asarray(K, dtype=np.float32)
        self._width, self._height = width, height
        self._max_depth_m = max_depth_m
        self._volume = None
        self._T_W_V = None  # volume pose (its voxel grid's origin and axes in the world)
        self._recent: deque = deque(maxlen=max(1, config.refill_frames))
        self.num_integrated = 0  # frames integrated since the volume was placed
        self.num_placements = 0

    @property
    def side_m(self) -> float:
        return self.config.resolution * self.config.voxel_size_m

    @property
    def is_empty(self) -> bool:
        return self.num_integrated == 0

    def _settings(self, T_W_V: np.ndarray):
        import cv2

        c = self.config
        settings = cv2.VolumeSettings(cv2.VolumeType_TSDF)
        settings.setCameraIntegrateIntrinsics(self._K)
        settings.setCameraRaycastIntrinsics(self._K)
        settings.setIntegrateWidth(self._width)
        settings.setIntegrateHeight(self._height)
        settings.setRaycastWidth(self._width)
        settings.setRaycastHeight(self._height)
        settings.setDepthFactor(1.0)
        settings.setMaxDepth(self._max_depth_m)
        settings.setVoxelSize(c.voxel_size_m)
        settings.setVolumeResolution(np.full(3, c.resolution, dtype=np.int32))
        settings.setTsdfTruncateDistance(c.truncation_voxels * c.voxel_size_m)
        settings.setMaxWeight(c.max_weight)
        settings.setVolumePose(T_W_V.astype(np.float32))
        return settings

    def place(self, T_W_C: np.ndarray) -> None:
        """Empty the model and centre it on the camera ``T_W_C``; refill it with recent frames."""
        import cv2

        c = self.config
        side = self.side_m
        R_W_V = T_W_C[:3, :3] @ _FLIP
        camera_V = np.array([0.5 * side, 0.5 * side, c.camera_depth_fraction * side])
        T_W_V = np.eye(4)
        T_W_V[:3, :3] = R_W_V
        T_W_V[:3, 3] = T_W_C[:3, 3] - R_W_V @ camera_V
        self._T_W_V = T_W_V
        self._volume = cv2.Volume(cv2.VolumeType_TSDF, self._settings(T_W_V))
        self.num_integrated = 0
        self.num_placements += 1
        for depth, T in list(self._recent):
            if self.contains(T):
                self._integrate(depth, T)

    def contains(self, T_W_C: np.ndarray) -> bool:
        """Whether the camera is inside the volume (with margin) and looks the right way."""
        if self._T_W_V is None:
            return False
        c = self.config
        T_V_C = np.linalg.inv(self._T_W_V) @ T_W_C
        margin = c.margin_voxels * c.voxel_size_m
        inside = np.all(T_V_C[:3, 3] > margin) and np.all(T_V_C[:3, 3] < self.side_m - margin)
        # Camera z axis against the volume's -z axis (the direction it was placed for).
        cos_view = -T_V_C[2, 2]
        return bool(inside and cos_view > np.cos(np.radians(c.max_view_angle_deg)))

    def integrate(self, depth: np.ndarray, T_W_C: np.ndarray) -> None:
        """Fuse a depth image taken at ``T_W_C``; re-place the volume first if it must move."""
        self._recent.append((depth, T_W_C.copy()))
        if not self.contains(T_W_C):
            self.place(T_W_C)  # refills with the recent frames, this one included
            return
        self._integrate(depth, T_W_C)

    def _integrate(self, depth: np.ndarray, T_W_C: np.ndarray) -> None:
        # One voxel along the volume's z axis: see the module docstring.
        T_shifted = T_W_C.copy()
        T_shifted[:3, 3] += self.config.voxel_size_m * self._T_W_V[:3, 2]
        self._volume.integrate(depth, T_shifted.astype(np.float32))
        self.num_integrated += 1

    def render(self, T_W_C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray-cast the model at ``T_W_C``: depth (float32, 0 = no surface) and normals
        (H x W x 4 float32 in the camera frame, NaN where there is no surface)."""
        points, normals = self._volume.raycast(T_W_C.astype(np.float32))
        depth = points[..., 2]
        valid = np.isfinite(depth) & (depth > 0)
        depth = np.where(valid, depth, 0.0).astype(np.float32)
        normals = np.where(valid[..., None], normals, np.nan).astype(np.float32)
        return depth, normals
