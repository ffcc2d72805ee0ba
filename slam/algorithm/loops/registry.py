"""The loop detector of each sensor kind, and the one a run's config asks for."""

from __future__ import annotations

from slam.algorithm.loops.base import LoopDetector
from slam.algorithm.loops.config import LoopClosureConfig
from slam.algorithm.loops.lidar import LidarLoopDetector
from slam.algorithm.loops.rgbd import RgbdLoopDetector

LOOP_DETECTORS: dict[str, type[LoopDetector]] = {
    "lidar": LidarLoopDetector,
    "rgbd": RgbdLoopDetector,
}
"""The detector of each sensor kind; ``loop_closure.method`` picks one ("auto": the sensor's)."""


def make_loop_detector(lc: LoopClosureConfig, sensor: str) -> LoopDetector | None:
    """The loop detector for a sensor (None when loop closure is off)."""
    if not lc.enabled:
        return None
    method = sensor if lc.method == "auto" else lc.method
    return LOOP_DETECTORS[method](lc)


__all__ = ["LOOP_DETECTORS", "make_loop_detector"]
