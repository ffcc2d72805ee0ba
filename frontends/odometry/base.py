"""Odometry interface and registry: frames in, sensor poses ``T_W_S`` out."""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Callable

import numpy as np

from frontends.errors import DatasetError
from frontends.frame import Frame

ODOMETRIES: dict[str, Callable[..., Odometry]] = {}

_ODOMETRY_MODULES: dict[str, str] = {
    "gt": "frontends.odometry.ground_truth",
    "kiss-icp": "frontends.odometry.kiss",
    "rgbd": "frontends.odometry.rgbd",
}


class Odometry(ABC):
    """Estimates the pose of each new frame relative to the first one (``T_W_S`` with W = S_0)."""

    @abstractmethod
    def register(self, frame: Frame) -> np.ndarray:
        """Consume the next frame and return its 4x4 float64 pose ``T_W_S``."""

    def map_points(self, frame: Frame) -> np.ndarray:
        """(N, 3) points in the sensor frame S that the map should hold for ``frame``, the frame
        :meth:`register` consumed last: the frame's own points unless the odometry corrects them
        (KISS-ICP returns its motion-compensated scan)."""
        return frame.points

    def take_covariance(self) -> np.ndarray | None:
        """6x6 covariance (GTSAM order ``[rx, ry, rz, tx, ty, tz]``) of the motion registered
        since the last call, and start a new interval; None when the odometry gives none."""
        return None


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
