"""What a finished pipeline hands to metrics: :class:`PipelineReport`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.algorithm.loops.base import LoopCandidate
from slam.algorithm.remap import RemapEvent


@dataclass(frozen=True)
class PipelineReport:
    """The results and statistics of a run of :class:`~slam.algorithm.pipeline.SlamPipeline`.

    Attributes:
        num_frames: frames processed.
        odometry_poses: (N, 4, 4) odometry poses ``T_W_S``.
        slam_poses: (N, 4, 4) final SLAM estimates ``T_W_S``.
        gt_poses: (N, 4, 4) ground truth in its own world frame with NaN rows where a frame has
            none, or None when no frame has one.
        timestamps: (N,) frame timestamps in seconds.
        loop_candidates: every loop candidate examined, with the pose graph's final verdict.
        remap_events: every remapping pass that moved a submap.
        submap_frame_counts: frames of each submap, ``{submap_id: count}``.
        neural_map: the final neural map.
        submaps: the encoded submaps (each with its original encoding), in submap order.
        timings_s: wall seconds of every call of each stage.
        stage_cpu_s: CPU seconds of the thread that ran each stage.
    """

    num_frames: int
    odometry_poses: np.ndarray
    slam_poses: np.ndarray
    gt_poses: np.ndarray | None
    timestamps: np.ndarray
    loop_candidates: list[LoopCandidate]
    remap_events: list[RemapEvent]
    submap_frame_counts: dict[int, int]
    neural_map: object
    submaps: list
    timings_s: dict[str, list[float]]
    stage_cpu_s: dict[str, float]
