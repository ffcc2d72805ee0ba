"""Keyframing policies: when a submap closes."""

from __future__ import annotations

import numpy as np

from frontends.frame import Frame
from slam.config import SubmapConfig
from slam.submaps import Keyframer


def _wall_view(index: int, half_width_m: float = 0.5) -> Frame:
    """A sensor 2 m in front of a wall (z = 2 in the sensor frame), seeing a 1 m x 1 m patch."""
    u = np.linspace(-half_width_m, half_width_m, 60)
    x, y = np.meshgrid(u, u)
    points = np.c_[x.ravel(), y.ravel(), np.full(x.size, 2.0)]
    normals = np.tile([0.0, 0.0, -1.0], (len(points), 1))
    return Frame(index=index, timestamp=0.1 * index, points=points, normals=normals)


def _pose(x_m: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x_m
    return T


def _closing_frames(cfg: SubmapConfig, step_m: float, frames: int) -> list[int]:
    keyframer = Keyframer(cfg)
    closed_at = []
    for i in range(frames):
        closed, _, _ = keyframer.add(_wall_view(i), _pose(step_m * i))
        if closed is not None:
            closed_at.append(i)
    return closed_at


def _cfg(**kw) -> SubmapConfig:
    base = {"max_distance_m": 100.0, "max_rotation_deg": 90.0, "max_range_m": 10.0}
    return SubmapConfig(**(base | kw))


def test_a_lingering_sensor_is_not_stored_again_and_again() -> None:
    """A frame count closes a static sensor's submap every max_frames frames (each one a copy
    of the same view); closing by covered surface keeps one submap."""
    assert _closing_frames(_cfg(max_frames=10), step_m=0.0, frames=45) == [10, 20, 30, 40]
    by_surface = _cfg(max_frames=1000, max_surface_views=2.0)
    assert _closing_frames(by_surface, step_m=0.0, frames=45) == []


def test_a_sweeping_sensor_closes_once_it_covers_the_surface_budget() -> None:
    # 5 cm per frame along a wall seen 1 m wide: the submap covers 2 views after ~20 frames
    closed_at = _closing_frames(_cfg(max_frames=1000, max_surface_views=2.0), 0.05, 80)
    assert 2 <= len(closed_at) <= 5
    gaps = np.diff([0, *closed_at])
    assert (gaps >= 15).all() and (gaps <= 25).all()
    # a larger budget gives proportionally longer submaps
    longer = _closing_frames(_cfg(max_frames=1000, max_surface_views=3.0), 0.05, 80)
    assert len(longer) < len(closed_at)
