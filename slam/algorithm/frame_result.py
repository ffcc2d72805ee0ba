"""What the pipeline reports for each frame it consumes (:meth:`SlamPipeline.process
<slam.algorithm.pipeline.SlamPipeline.process>`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from slam.algorithm.loops.base import LoopCandidate
from slam.algorithm.remap import RemapEvent

if TYPE_CHECKING:
    from slam.algorithm.merge.relocalise import Relocalisation


@dataclass
class FrameResult:
    """What happened at one frame.

    Attributes:
        index: frame index.
        T_W_S_odometry: odometry pose.
        T_W_S: the SLAM estimate at this time (anchor estimate composed with the relative pose).
        submap_id: the submap the frame belongs to.
        closed_submap_id: the submap this frame closed, or None.
        loops: loop candidates that became known at this frame (those of the submap closed
            before ``closed_submap_id``: the main thread takes the submap worker's results one
            submap later, see :mod:`slam.algorithm.graph_view`).
        remap: the remapping pass that came with them, or None (always None with a threaded
            map worker: see :attr:`SlamPipeline.remapper` for every pass).
        loop_added: an accepted loop went into the pose graph, or the session was relocalised,
            and it became known at this frame (every anchor, so every frame's estimate, may have
            moved).
        relocalised: the session's placement in a stored map, at the frame it became known.
        frame_s: wall seconds the pipeline spent on this frame.
        odometry_s: of which the odometry's.
    """

    index: int
    T_W_S_odometry: np.ndarray
    T_W_S: np.ndarray
    submap_id: int
    closed_submap_id: int | None = None
    loops: list[LoopCandidate] = field(default_factory=list)
    remap: RemapEvent | None = None
    loop_added: bool = False
    relocalised: Relocalisation | None = None
    frame_s: float = 0.0
    odometry_s: float = 0.0
