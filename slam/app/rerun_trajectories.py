"""When a recording sends a growing trajectory again.

Each log of a polyline has a fixed cost and a polyline of N poses costs N, so re-logging a
growing trajectory every frame would log a quadratic amount of data: a trajectory of N poses is
re-logged every ``ceil(N / relog_points)`` frames and at least :data:`TRAJECTORY_MIN_RELOG_FRAMES`
apart, at once when its already-logged part moved (an optimisation), and the newest one held back
is sent on a flush.
"""

from __future__ import annotations

import math

import numpy as np

TRAJECTORY_MIN_RELOG_FRAMES = 5
"""A growing (not moved) trajectory is re-logged at most this often: each log has a fixed cost."""


class TrajectoryThrottle:
    """Which trajectories are due to be logged, by name.

    Args:
        relog_points: a growing trajectory of N poses is due every ``ceil(N / relog_points)``
            frames.
        move_m: a trajectory whose already-logged part moved by more than this is due at once.
    """

    def __init__(self, relog_points: int, move_m: float) -> None:
        self.relog_points = max(1, relog_points)
        self.move_m = move_m
        self.pending: dict[str, np.ndarray] = {}
        """The newest positions of each trajectory that were not logged (for a flush)."""
        self._logged_frame: dict[str, int] = {}
        self._logged: dict[str, np.ndarray] = {}

    def due(self, name: str, positions: np.ndarray, frame: int) -> bool:
        """Whether ``positions`` should be logged at ``frame``; if not and they grew, they are
        held in :attr:`pending`."""
        last = self._logged.get(name)
        if last is None or self._moved(last, positions):
            return True
        every = max(TRAJECTORY_MIN_RELOG_FRAMES, math.ceil(len(positions) / self.relog_points))
        if len(positions) != len(last) and frame - self._logged_frame[name] >= every:
            return True
        if len(positions) != len(last):
            self.pending[name] = positions
        return False

    def logged(self, name: str, positions: np.ndarray, frame: int) -> None:
        """Record that ``positions`` were logged at ``frame``."""
        self._logged_frame[name] = frame
        self._logged[name] = positions
        self.pending.pop(name, None)

    def _moved(self, logged: np.ndarray, positions: np.ndarray) -> bool:
        """Whether the already-logged part of a trajectory changed (an optimisation moved it)."""
        n = min(len(logged), len(positions))
        if len(positions) < len(logged):
            return True
        return n > 0 and float(np.abs(positions[:n] - logged[:n]).max()) > self.move_m
