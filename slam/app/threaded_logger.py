"""A :class:`~slam.algorithm.viz.Logger` that records on a thread of its own.

The main thread runs the odometry: whatever else it does between two scans delays the next one.
Recording a frame (subsampling and colouring the scan, encoding images, sending columns, meshes
and voxel snapshots at submap closes) took about 4 ms a frame of the generated street at full
length, 9-12 % of the run's rate. :class:`ThreadedLogger` hands every call to one background
thread instead, in the order they were made; the main thread only evaluates what reads the
pipeline's state (the ``*_from`` callables, as :class:`~slam.algorithm.viz.Logger` does), so the
values logged are those of the moment of the call. All calls run on that one thread (Rerun's
current time is per thread). The queue is bounded: a recording that falls behind holds the run
up instead of piling up frames in memory. An error of a call is raised on the main thread at
the next call or at :meth:`close`.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

from slam.algorithm.viz import Logger

MAX_PENDING_CALLS = 64
"""Calls queued at most (a frame makes about six); the next one waits for the oldest."""


class ThreadedLogger(Logger):
    """Runs ``inner``'s methods in call order on one background thread (module docstring)."""

    def __init__(self, inner: Logger, max_pending: int = MAX_PENDING_CALLS) -> None:
        self.inner = inner
        self.viewer_url = inner.viewer_url
        self._max_pending = max(1, max_pending)
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="recording")
        self._pending: deque[Future] = deque()
        self._closed = False

    def _call(self, method: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        if self._closed:
            raise RuntimeError("the recording is closed")
        self._collect(keep=self._max_pending - 1)
        self._pending.append(self._pool.submit(method, *args, **kwargs))

    def _collect(self, keep: int) -> None:
        """Take the finished calls off the queue, waiting for the oldest ones until at most
        ``keep`` are left; raises the first error among them."""
        while self._pending and (self._pending[0].done() or len(self._pending) > keep):
            self._pending.popleft().result()

    def set_time(self, frame_index, timestamp_s):
        self._call(self.inner.set_time, frame_index, timestamp_s)

    def log_scan(self, points_W, colors=None, T_W_S=None):
        self._call(self.inner.log_scan, points_W, colors, T_W_S)

    def log_sensor(self, T_W_S, intrinsics=None, rgb=None, depth_m=None):
        self._call(self.inner.log_sensor, T_W_S, intrinsics, rgb, depth_m)

    def log_trajectory(self, name, positions_W):
        self._call(self.inner.log_trajectory, name, positions_W)

    def log_loop_closures(self, accepted, rejected=()):
        self._call(self.inner.log_loop_closures, accepted, rejected)

    def log_map(self, voxel_centers_W, voxel_values, mesh=None):
        self._call(self.inner.log_map, voxel_centers_W, voxel_values, mesh)

    def log_metrics(self, **scalars):
        self._call(self.inner.log_metrics, **scalars)

    def log_stored_map(self, mesh_path):
        self._call(self.inner.log_stored_map, mesh_path)

    def log_map_anchoring(self, segments):
        self._call(self.inner.log_map_anchoring, segments)

    def flush(self):
        """Queue the inner flush and wait for it (a live viewer then shows the run so far)."""
        self._call(self.inner.flush)
        self._collect(keep=0)

    def close(self):
        """Run every queued call, close the inner logger (also after a failed call) and stop
        the thread; raises the first error of a queued call."""
        if self._closed:
            return
        self._closed = True
        try:
            self._collect(keep=0)
        finally:
            try:
                self._pool.submit(self.inner.close).result()
            finally:
                self._pool.shutdown(wait=True, cancel_futures=True)
