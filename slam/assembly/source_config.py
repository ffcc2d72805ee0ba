"""What a run reads and how: the source's options (:class:`SourceConfig`) and the generated
sequence's (:class:`GeneratedConfig`). Part of :class:`slam.assembly.config.RunConfig`."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator

from common.config import Strict
from frontends.sources import SOURCES
from frontends.sources._io import DepthOptions

SOURCE_NAMES = ", ".join(SOURCES)


class KittiOptions(Strict):
    """Options of the KITTI source."""

    correct_vertical_angle: bool | Literal["auto"] = Field(
        "auto",
        description="apply KISS-ICP's 0.205 deg vertical-angle correction of KITTI's HDL-64E "
        "scans: auto decides from the road in the scans (metrics.json, "
        "input.kitti_vertical_angle_correction, says what and why; on where the road does not "
        "tell); true or false is kept, with a warning where the road disagrees",
    )
    max_range_m: float | None = Field(
        None, description="drop points farther than this when loading (None: keep all)"
    )


class CameraIntrinsics(Strict):
    """Pinhole intrinsics of the depth/colour images, in pixels."""

    fx: float = Field(gt=0, description="focal length along x (pixels)")
    fy: float = Field(gt=0, description="focal length along y (pixels)")
    cx: float = Field(description="principal point x (pixels)")
    cy: float = Field(description="principal point y (pixels)")
    width: int = Field(640, ge=1, le=16384, description="image width (pixels) (1 to 16384)")
    height: int = Field(480, ge=1, le=16384, description="image height (pixels) (1 to 16384)")


class TumOptions(Strict):
    """Options of the TUM and ICL-NUIM sources."""

    max_time_difference_s: float = Field(
        0.02, gt=0, description="largest colour/depth/ground-truth timestamp gap when pairing"
    )
    intrinsics: CameraIntrinsics | None = Field(
        None,
        description="TUM: camera intrinsics (None: the folder's intrinsics.txt, else the "
        "published calibration of freiburg1/2/3 picked by the sequence name, else 525/525)",
    )
    depth_scale: float | None = Field(
        None, gt=0, description="TUM: depth PNG units per metre (None: intrinsics.txt, else 5000)"
    )
    allow_outside_paths: bool = Field(
        False,
        description="TUM: accept rgb.txt/depth.txt/associations.txt entries that leave the "
        "sequence folder ('../', absolute paths); refused by default",
    )


class LidarOptions(Strict):
    """Options of the ``lidar`` source (a kiss_icp.datasets dataloader)."""

    dataloader: str = Field(
        "generic",
        description="kiss_icp dataloader: generic, rosbag, mcap, ouster, nuscenes, mulran, ncd, "
        "helipr, boreas, apollo, nclt, kitti, kitti_raw, or npy (a folder of .npy scans)",
    )
    sequence: str | None = Field(
        None, description="sequence name for kitti, kitti_raw, nuscenes and helipr"
    )
    topic: str | None = Field(
        None, description="PointCloud2 topic of a bag/MCAP file (needed when it has several)"
    )
    gt_poses: Path | None = Field(
        None,
        description="ground truth when the dataloader has none: KITTI rows (one per scan) or a "
        "TUM trajectory (associated by timestamp), sensor frame",
    )
    nominal_rate_hz: float = Field(
        10.0, gt=0, description="scan rate for timestamps when the dataloader gives none"
    )
    max_range_m: float | None = Field(
        None, gt=0, description="drop points farther than this when loading (None: keep all)"
    )
    scale_from_first_scan: bool = Field(
        False,
        description="set the ranges, submap length and voxel sizes that the config leaves unset "
        "from the extent of the first scan (slam/lidar_scale.py)",
    )


class SourceConfig(Strict):
    """Which recorded sequence to read and how."""

    dataset: str = Field(
        "generated", description="source name, one of frontends.sources.SOURCES: " + SOURCE_NAMES
    )
    sequence: str | None = Field(
        None, description="sequence name inside the dataset root (e.g. '00', 'lr-kt3', 'seq-01')"
    )
    root: Path | None = Field(
        None, description="dataset root folder; for generated data, the cache folder"
    )
    frames: str | None = Field(
        None, description="frame range 'A:B[:STEP]' (Python slice syntax; empty parts allowed)"
    )
    min_points: int = Field(
        50,
        ge=0,
        description="a frame with fewer points (an empty, truncated or broken scan or depth "
        "image) is skipped with a warning and listed in metrics.json's input.skipped_frames",
    )
    depth: DepthOptions = Field(
        default_factory=DepthOptions, description="how RGB-D depth images are lifted to points"
    )
    kitti: KittiOptions = Field(default_factory=KittiOptions, description="KITTI options")
    tum: TumOptions = Field(default_factory=TumOptions, description="TUM / ICL-NUIM options")
    lidar: LidarOptions = Field(
        default_factory=LidarOptions, description="options of the 'lidar' source"
    )

    @field_validator("dataset")
    @classmethod
    def _known_source(cls, name: str) -> str:
        if name not in SOURCES:
            raise ValueError(f"unknown source '{name}'; choose one of: {SOURCE_NAMES}")
        return name


class GeneratedConfig(Strict):
    """A generated sequence (used when ``source.dataset`` is ``generated``)."""

    kind: Literal["lidar", "rgbd"] = Field("rgbd", description="sensor of the generated sequence")
    num_frames: int = Field(240, ge=2, le=5000, description="frames to generate (2 to 5000)")
    seed: int = Field(0, description="random seed of the scene and the sensor noise")
    trajectory: Literal["loop", "kitti"] = Field(
        "loop",
        description="LiDAR: one lap around a block, or a window of a real KITTI trajectory",
    )
    kitti_poses: Path | None = Field(
        None, description="LiDAR 'kitti' trajectory: the KITTI poses/NN.txt file"
    )
    kitti_calib: Path | None = Field(
        None, description="LiDAR 'kitti' trajectory: its sequences/NN/calib.txt"
    )
    start: int = Field(0, ge=0, description="LiDAR 'kitti' trajectory: first frame")
    step: int = Field(1, ge=1, le=1000, description="LiDAR 'kitti' trajectory: step, <= 1000")
    azimuth_steps: int = Field(
        2048, ge=64, le=16384, description="LiDAR firings per revolution (2048 ~ HDL-64E; <= 16384)"
    )
    terrain_relief_m: float = Field(
        0.0,
        ge=0,
        le=1000,
        description=(
            "LiDAR street: height (m) of the hills that rise beside the road, from 7 m off the "
            "path to full height 25 m off it. The road always follows the trajectory's own "
            "elevation (the real KITTI profile for 'kitti'); 0 keeps the ground beside it level "
            "with the road; at most 1000 m"
        ),
    )
    street_style: Literal["standard", "sparse", "periodic"] = Field(
        "standard",
        description="LiDAR street layout: 'standard' (irregular buildings, cars, poles, trees), "
        "'sparse' (long blank walls far apart, a rare building, few cars) or 'periodic' (one "
        "identical building and tree every 16 m, the aliasing of a regular avenue)",
    )
    range_noise_m: float = Field(
        0.02, ge=0, description="LiDAR: std-dev of the gaussian range noise (m)"
    )
    dropout: float = Field(
        0.02, ge=0, lt=1, description="LiDAR: probability that a valid return is lost"
    )
    width: int = Field(640, ge=32, le=4096, description="RGB-D image width (32 to 4096)")
    height: int = Field(480, ge=32, le=4096, description="RGB-D image height (32 to 4096)")
