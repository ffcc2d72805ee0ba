"""The logging interface the pipeline reports to, and its null implementation.

The pipeline calls a :class:`Logger` unconditionally; whether anything is recorded depends only on
which implementation was constructed (Rerun, or :class:`NullLogger`). Algorithm objects never log
themselves: the runner hands their results to the logger.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import trimesh

from frontends.frame import Intrinsics

Segments = Sequence[tuple[np.ndarray, np.ndarray]]
"""Line segments as pairs of world positions."""


class Logger(ABC):
    """What a run reports. All poses are 4x4 float64 ``T_W_*``, all points in the world frame."""

    viewer_url: str | None = None
    """The page a user opens to watch the run live (a served web viewer), else None."""

    @abstractmethod
    def set_time(self, frame_index: int, timestamp_s: float) -> None:
        """Set the current time on the ``frame`` and ``sensor_time`` timelines."""

    @abstractmethod
    def log_scan(
        self,
        points_W: np.ndarray,
        colors: np.ndarray | None = None,
        T_W_S: np.ndarray | None = None,
    ) -> None:
        """The current (downsampled) scan in the world frame; with ``T_W_S``, the points are in
        the sensor frame and the logger places the ones it shows (a logger that subsamples
        then transforms only those)."""

    @abstractmethod
    def log_sensor(
        self,
        T_W_S: np.ndarray,
        intrinsics: Intrinsics | None = None,
        rgb: np.ndarray | None = None,
        depth_m: np.ndarray | None = None,
    ) -> None:
        """The sensor pose; for RGB-D also a pinhole with its colour and depth images."""

    @abstractmethod
    def log_trajectory(self, name: str, positions_W: np.ndarray) -> None:
        """A whole trajectory polyline; ``name`` is ``odometry``, ``optimized`` or ``gt``."""

    @abstractmethod
    def log_loop_closures(self, accepted: Segments, rejected: Segments = ()) -> None:
        """Loop edges as pairs of world positions (accepted and rejected candidates)."""

    @abstractmethod
    def log_map(
        self,
        voxel_centers_W: np.ndarray,
        voxel_values: np.ndarray,
        mesh: trimesh.Trimesh | None = None,
    ) -> None:
        """The neural map: voxel centres with a scalar each (weight), optionally its mesh."""

    @abstractmethod
    def log_metrics(self, **scalars: float) -> None:
        """Scalar time series under ``metrics/<name>``."""

    def log_map_from(
        self,
        snapshot: Callable[[], tuple[np.ndarray, np.ndarray, trimesh.Trimesh | None]],
    ) -> None:
        """:meth:`log_map` of what ``snapshot()`` returns. The pipeline passes the costly part
        (voxel centres, a mesh) as a callable so that a logger recording nothing never pays it."""
        self.log_map(*snapshot())

    def log_metrics_from(self, scalars: Callable[[], dict[str, float]]) -> None:
        """:meth:`log_metrics` of what ``scalars()`` returns (e.g. the error so far)."""
        self.log_metrics(**scalars())

    def log_stored_map(self, mesh_path: Path) -> None:  # noqa: B027 - optional hook
        """The mesh of the map a run continues (``slam.run --map``), in the map's frame: the
        run appears on it once it is relocalised. Read from ``mesh_path`` by a logger that
        shows it, so a logger recording nothing never pays for it."""

    def log_map_anchoring(self, segments: Segments) -> None:  # noqa: B027 - optional hook
        """Which stored submaps hold a run in a stored map (``slam.run --map``): a segment from
        each map-anchored live submap's anchor to each stored submap its registration was made
        to (anchor positions in the map's frame); the whole set, whenever it changes."""

    def flush(self) -> None:  # noqa: B027 - optional hook
        """Send what the logger holds back, so that a live viewer shows the run so far (before
        the run pauses with a viewer open); :meth:`close` does it too."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Flush and close the recording."""


class NullLogger(Logger):
    """Records nothing."""

    def set_time(self, frame_index, timestamp_s):
        pass

    def log_scan(self, points_W, colors=None, T_W_S=None):
        pass

    def log_sensor(self, T_W_S, intrinsics=None, rgb=None, depth_m=None):
        pass

    def log_trajectory(self, name, positions_W):
        pass

    def log_loop_closures(self, accepted, rejected=()):
        pass

    def log_map(self, voxel_centers_W, voxel_values, mesh=None):
        pass

    def log_metrics(self, **scalars):
        pass

    def log_map_from(self, snapshot):
        pass

    def log_metrics_from(self, scalars):
        pass
