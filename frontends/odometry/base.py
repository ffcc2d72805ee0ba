"""Odometry interface and registry: frames in, one :class:`OdometryResult` per frame out."""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from frontends.errors import DatasetError
from frontends.frame import Frame

ODOMETRIES: dict[str, Callable[..., Odometry]] = {}

_ODOMETRY_MODULES: dict[str, str] = {
    "gt": "frontends.odometry.ground_truth",
    "kiss-icp": "frontends.odometry.kiss",
    "rgbd": "frontends.odometry.rgbd",
}


@dataclass(frozen=True)
class OdometryResult:
    """What an odometry reports for one frame.

    Attributes:
        T_W_S: 4x4 float64 pose of the frame (W = the first sensor frame).
        points: (N, 3) points in the sensor frame S that the map should hold for this frame when
            the odometry corrected them (KISS-ICP's motion-compensated scan), or None for the
            frame's own points.
        covariance: 6x6 covariance (GTSAM order ``[rx, ry, rz, tx, ty, tz]``, right
            perturbation) of the motion from the frame of the latest
            :meth:`Odometry.restart_covariance` (or the first frame) to this one; None when the
            odometry gives none.
    """

    T_W_S: np.ndarray
    points: np.ndarray | None = None
    covariance: np.ndarray | None = None

    def map_points(self, frame: Frame) -> np.ndarray:
        """The points the map should hold for ``frame`` (the frame this result is of)."""
        return frame.points if self.points is None else self.points


class Odometry(ABC):
    """Estimates the pose of each new frame relative to the first one (``T_W_S`` with W = S_0).

    Attributes:
        num_failures: frames whose registration failed and whose pose was extrapolated instead,
            or None for an odometry that cannot tell (KISS-ICP always returns a pose).
        drifts: whether the poses can drift from the truth; False only for the truth itself,
            whose run then measures no up direction: a measurement (about 0.1 deg off per scan
            on generated streets) could only move exact poses away from the truth.
    """

    num_failures: int | None = None
    drifts: bool = True

    @abstractmethod
    def register(self, frame: Frame) -> OdometryResult:
        """Consume the next frame and return its pose, map points and covariance."""

    def restart_covariance(self) -> None:  # noqa: B027 - optional hook
        """Make the frame registered last the origin of the motion whose covariance later
        results carry (the pipeline calls it when that frame anchors a new submap, so each
        odometry edge of the pose graph gets the covariance of its own motion)."""

    def child_cpu_s(self) -> float:
        """CPU seconds used so far by a child process the odometry runs in (0: it runs in this
        process, whose own CPU time counts it)."""
        return 0.0

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release what the odometry holds outside this object (a child process); no frame may
        follow."""


def register_odometry(name: str) -> Callable[[type[Odometry]], type[Odometry]]:
    """Class decorator adding an odometry to :data:`ODOMETRIES` under ``name``."""

    def wrap(cls: type[Odometry]) -> type[Odometry]:
        ODOMETRIES[name] = cls
        return cls

    return wrap


def make_odometry(name: str, **kwargs) -> Odometry:
    """Build the odometry registered as ``name`` (keyword arguments go to its constructor)."""
    module = _ODOMETRY_MODULES.get(name)
    if module is None:
        known = ", ".join(sorted(_ODOMETRY_MODULES))
        raise DatasetError(f"unknown odometry '{name}'; choose one of: {known}")
    importlib.import_module(module)
    return ODOMETRIES[name](**kwargs)
