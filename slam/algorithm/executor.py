"""The pipeline's concurrency in one place: its two workers, the snapshots that cross between
threads and the per-thread timings.

Three threads take part in a run (one with ``threaded`` off, where every job runs inside its
submission):

- the *main* thread runs the odometry and the keyframing decision and submits one job per frame;
- the *submap worker* absorbs each frame's points, closes submaps, detects loops and owns the pose
  graph; after each closed submap it publishes a :class:`~slam.algorithm.graph_view.GraphSnapshot`
  that the main thread applies to its :class:`~slam.algorithm.graph_view.GraphView` one submap
  late (at the next close, a point fixed by the frames, not by the timing);
- the *map worker* encodes, fuses and remaps; after each job it returns what it did and, when a
  viewer asked for them (:meth:`Executor.request_map_snapshots`), publishes a
  :class:`MapSnapshot` of the map, which the main thread reads without waiting for anything.

Nothing is written by two threads: each thread books its stages in its own
:class:`StageTimings`, merged by :meth:`Executor.timings` once the workers have stopped, and
everything else crosses as an immutable snapshot, a job's argument or a job's result.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from slam.algorithm.graph_view import GraphSnapshot, GraphView
from slam.algorithm.map_worker import MapWorker, job_result
from slam.algorithm.remap import RemapEvent

SUBMAP_QUEUE_FRAMES = 32
"""Frames (a 3 MB scan each) queued for the submap worker before the main thread waits: 32 cover
a loop verification (full-length LiDAR run: waited 30 s with 8, 15 s with 32)."""

STAGES = (
    "odometry",
    "keyframing",
    "loop_detection",
    "pose_graph",
    "mapping",
    "remap",
    "map_logging",
    "map_worker_wait",
    "submap_worker_wait",
)
"""Stages every report lists, booked or not."""


def clock() -> tuple[float, float]:
    """(wall, CPU time of the calling thread) in seconds."""
    return time.perf_counter(), time.thread_time()


MESH_S_PER_VOXEL_PRIOR = 2.5e-4
"""Seconds a mesh extraction takes per voxel of the map before one has been timed (a whole
room's first mesh on 2 cores of an x86 VM); each extraction replaces it with its own figure, so
that a viewer's mesh is extracted only when the run's time share can pay for it."""


class StageTimings:
    """Wall seconds of every call of each stage and the CPU seconds of the thread that ran it,
    booked by one thread only."""

    def __init__(self) -> None:
        self.wall_s: dict[str, list[float]] = defaultdict(list)
        self.cpu_s: dict[str, float] = defaultdict(float)

    def book(self, name: str, start: tuple[float, float]) -> tuple[float, float]:
        """Book the time since ``start`` (a :func:`clock` reading) to ``name``; returns the new
        reading."""
        now = clock()
        self.wall_s[name].append(now[0] - start[0])
        self.cpu_s[name] += now[1] - start[1]
        return now


class SubmapJobResult(NamedTuple):
    """What one frame's submap job hands back to the main thread.

    Attributes:
        snapshot: the graph after the submap the frame closed (None when it closed none).
        surface_full: the open submap covers ``max_surface_views`` times its largest view (the
            keyframing decision of the next frame needs it when it closes by surface).
    """

    snapshot: GraphSnapshot | None
    surface_full: bool


@dataclass(frozen=True)
class MapSnapshotRequest:
    """What a viewer wants of the map after each map job.

    Attributes:
        mesh_every_submaps: a mesh after every n-th encoded submap.
        mesh_after_remap: a mesh after every remapping pass that moved a submap.
        mesh_time_share: a mesh only while the meshes so far took at most this share of the
            time since the request (meshing the whole map costs more as it grows).
    """

    mesh_every_submaps: int
    mesh_after_remap: bool
    mesh_time_share: float = 1.0


@dataclass(frozen=True)
class MapSnapshot:
    """The map as the latest finished map job left it.

    Attributes:
        job: 1, 2, ... the map job (= closed submap) it was taken after.
        voxel_centers: (V, 3) voxel centres in the world frame.
        voxel_weights: (V,) fusion weights.
        mesh: the mesh extracted after the latest job that extracted one, or None.
        mesh_job: the job ``mesh`` was extracted after (0: none yet).
    """

    job: int
    voxel_centers: np.ndarray
    voxel_weights: np.ndarray
    mesh: object | None
    mesh_job: int


class Executor:
    """The submap and map workers, the main thread's graph view and the timings of all three
    threads (see the module docstring)."""

    def __init__(self, threaded: bool) -> None:
        self.submap_worker = MapWorker(
            threaded=threaded, max_pending=SUBMAP_QUEUE_FRAMES, name="submap-worker"
        )
        self.map_worker = MapWorker(threaded=threaded, name="map-worker")
        self.view = GraphView()
        self.main_timings = StageTimings()
        self.submap_timings = StageTimings()
        self.map_timings = StageTimings()
        self._unsynced: deque[Future] = deque()  # close jobs whose snapshot is not applied yet
        self._request: MapSnapshotRequest | None = None
        self._map_jobs = 0  # the map worker's
        self._mesh: tuple[object | None, int] = (None, 0)  # the map worker's
        self._mesh_s = 0.0  # the map worker's: seconds spent extracting meshes
        self._mesh_s_per_voxel = MESH_S_PER_VOXEL_PRIOR  # the map worker's estimate
        self._requested_at = 0.0
        self._latest_lock = threading.Lock()
        self._latest: MapSnapshot | None = None
        self._submitted = False
        self._closed = False

    @property
    def threaded(self) -> bool:
        return self.submap_worker.threaded

    # --- main thread ---------------------------------------------------------------------------

    def request_map_snapshots(self, request: MapSnapshotRequest) -> None:
        """Have the map worker publish a :class:`MapSnapshot` after each job (before the first
        frame: the map worker reads the request without a lock)."""
        if self._submitted:
            raise RuntimeError("request_map_snapshots() after the first frame")
        self._request = request
        self._requested_at = time.perf_counter()

    def submit_frame(self, job: Callable[..., SubmapJobResult], *args: Any, closes: bool) -> Future:
        """Queue a frame's submap job; with ``closes`` (the frame closes a submap) the snapshot
        of the submap closed before it is applied to :attr:`view`. The wait for the worker is
        booked as ``submap_worker_wait``."""
        self._submitted = True
        start = clock()
        future = self.submap_worker.submit(job, *args)
        if closes:
            self._unsynced.append(future)
            while len(self._unsynced) > 1:
                self._apply(self._unsynced.popleft())
        if self.threaded:
            self.main_timings.book("submap_worker_wait", start)
        return future

    def _apply(self, future: Future) -> None:
        snapshot = job_result(future).snapshot
        assert snapshot is not None
        self.view.apply(snapshot)

    def sync(self) -> None:
        """Wait for both workers and apply every snapshot: the view is then exact."""
        self.submap_worker.drain()
        self.map_worker.drain()
        while self._unsynced:
            self._apply(self._unsynced.popleft())

    def close_submap_worker(self) -> None:
        """Let the submap worker finish its queue and stop; every snapshot is applied."""
        start = clock()
        self.submap_worker.close()
        while self._unsynced:
            self._apply(self._unsynced.popleft())
        self.main_timings.book("submap_worker_wait", start)

    def close_map_worker(self) -> None:
        """Let the map worker finish its queue and stop."""
        start = clock()
        self.map_worker.close()
        self.main_timings.book("map_worker_wait", start)
        self._closed = True

    def abort(self) -> None:
        """Stop both workers without running their queued jobs (the run was interrupted or
        failed): only the job each is running is waited for. Errors of jobs are not raised."""
        self.submap_worker.cancel()
        self.map_worker.cancel()
        self._unsynced.clear()

    def latest_map(self) -> MapSnapshot | None:
        """The map as the latest finished map job left it (None before the first, or when no
        snapshot was requested); never waits for a worker."""
        with self._latest_lock:
            return self._latest

    def timings(self) -> tuple[dict[str, list[float]], dict[str, float]]:
        """Every stage's wall seconds per call and CPU seconds, merged over the threads (the
        workers' once both are closed, the main thread's alone before)."""
        parts = [self.main_timings]
        if self._closed or not self.threaded:
            parts = [self.submap_timings, self.map_timings, self.main_timings]
        wall_s: dict[str, list[float]] = {name: [] for name in STAGES}
        cpu_s: dict[str, float] = {}
        for part in parts:
            for name, values in part.wall_s.items():
                wall_s.setdefault(name, []).extend(values)
            for name, seconds in part.cpu_s.items():
                cpu_s[name] = cpu_s.get(name, 0.0) + seconds
        return wall_s, cpu_s

    # --- submap worker -------------------------------------------------------------------------

    def submit_map_job(self, job: Callable[..., RemapEvent | None], *args: Any) -> Future:
        """Queue a map job (from the submap worker); the wait is booked as ``map_worker_wait``
        (only when the map worker is two submaps behind)."""
        start = clock()
        future = self.map_worker.submit(job, *args)
        self.submap_timings.book("map_worker_wait", start)
        return future

    # --- map worker ----------------------------------------------------------------------------

    def publish_map(self, neural_map, remap: RemapEvent | None) -> None:
        """After a map job: publish a :class:`MapSnapshot` when a viewer asked for one (the
        extraction is booked as ``map_logging`` on the map worker)."""
        self._map_jobs += 1
        request = self._request
        if request is None:
            return
        start = clock()
        moved = remap is not None and remap.num_moved > 0
        periodic = self._map_jobs % request.mesh_every_submaps == 0
        budget_s = request.mesh_time_share * (start[0] - self._requested_at)
        wanted = periodic or (moved and request.mesh_after_remap)
        voxels = max(1, neural_map.num_voxels)
        affordable = self._mesh_s + self._mesh_s_per_voxel * voxels <= budget_s
        if wanted and (affordable or request.mesh_time_share >= 1.0):
            self._mesh = (neural_map.extract_mesh(), self._map_jobs)
            took_s = time.perf_counter() - start[0]
            self._mesh_s += took_s
            self._mesh_s_per_voxel = took_s / voxels
        centers, weights = neural_map.voxel_centers()
        snapshot = MapSnapshot(
            job=self._map_jobs,
            voxel_centers=np.asarray(centers),
            voxel_weights=np.asarray(weights, dtype=np.float64),
            mesh=self._mesh[0],
            mesh_job=self._mesh[1],
        )
        with self._latest_lock:
            self._latest = snapshot
        self.map_timings.book("map_logging", start)
