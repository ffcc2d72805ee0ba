"""Configuration of the algorithm as a whole: one section per stage, each defined beside its
stage. Every model forbids unknown keys, so a typo in a YAML file is an error that names the key.
The run's configuration (:class:`slam.assembly.config.RunConfig`) composes these sections with
the sources, odometry, map, viewer and output settings.
"""

from __future__ import annotations

from pydantic import Field

from common.config import Strict
from slam.algorithm.graph.config import GravityConfig, PoseGraphConfig
from slam.algorithm.loops.config import LidarLoopConfig, LoopClosureConfig, RgbdLoopConfig
from slam.algorithm.remap import RemapConfig
from slam.algorithm.submap_config import SubmapConfig

__all__ = [
    "GravityConfig",
    "LidarLoopConfig",
    "LoopClosureConfig",
    "PipelineConfig",
    "PoseGraphConfig",
    "RemapConfig",
    "RgbdLoopConfig",
    "SubmapConfig",
]


class PipelineConfig(Strict):
    """What :class:`~slam.algorithm.pipeline.SlamPipeline` runs with (the application's run
    configuration holds the same sections at its top level)."""

    submaps: SubmapConfig = Field(default_factory=SubmapConfig, description="keyframing")
    loop_closure: LoopClosureConfig = Field(
        default_factory=LoopClosureConfig, description="loop detection and verification"
    )
    pose_graph: PoseGraphConfig = Field(default_factory=PoseGraphConfig, description="pose graph")
    remap: RemapConfig = Field(default_factory=RemapConfig, description="remapping")
    map_worker: bool = Field(
        True,
        description="run keyframing, normals, loop detection and the pose graph on one worker "
        "thread and encoding, fusion and remapping on another while the caller runs the "
        "odometry; results do not depend on it (each worker applies its jobs in submission "
        "order)",
    )
