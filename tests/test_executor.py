"""The pipeline's workers and executor (slam/algorithm/map_worker.py, executor.py) on real
threads: backpressure, a failing job, shutdown under a signal, the snapshots one submap late and
per-thread timings. Each test takes well under a second."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from slam.algorithm.executor import Executor, MapSnapshotRequest, SubmapJobResult, clock
from slam.algorithm.graph_view import GraphSnapshot
from slam.algorithm.map_worker import MapWorker
from tests.helpers import python_sigint

WAIT_S = 5.0
"""Longest a test waits for something that should happen at once."""


def test_submit_blocks_while_max_pending_jobs_are_queued_or_running() -> None:
    worker = MapWorker(threaded=True, max_pending=2)
    release = threading.Event()
    worker.submit(release.wait, WAIT_S)
    worker.submit(lambda: None)
    submitted = threading.Event()
    blocked = threading.Thread(target=lambda: (worker.submit(lambda: None), submitted.set()))
    blocked.start()
    assert not submitted.wait(0.3)  # two jobs pending: the third waits
    release.set()
    assert submitted.wait(WAIT_S)
    blocked.join()
    worker.close()
    assert worker.cpu_s is not None


def test_a_failing_job_is_raised_at_the_next_submit_and_drain_and_the_worker_stops() -> None:
    worker = MapWorker(threaded=True, max_pending=4)
    ran: list[int] = []

    def fail() -> None:
        raise ValueError("encoding failed")

    failed = worker.submit(fail)
    assert failed.exception(timeout=WAIT_S) is not None
    with pytest.raises(ValueError, match="encoding failed"):
        worker.submit(ran.append, 1)
    worker.submit(ran.append, 2)
    worker.drain()  # the failure was raised once; later jobs run
    assert ran == [2]
    worker.submit(fail)
    with pytest.raises(ValueError, match="encoding failed"):
        worker.drain()
    worker.close()


def test_an_inline_worker_raises_inside_submit() -> None:
    worker = MapWorker(threaded=False)
    with pytest.raises(ZeroDivisionError):
        worker.submit(lambda: 1 / 0)
    assert worker.submit(lambda: 3).result() == 3


def test_ctrl_c_while_waiting_on_a_full_queue_stops_without_running_the_queue() -> None:
    """SIGINT, sent to the process (the kernel may hand it to any thread), reaches the main
    thread blocked in submit (backpressure); abort() then returns as soon as the running job
    ends, and the queued jobs never run."""
    executor = Executor(threaded=True)
    release = threading.Event()
    ran: list[int] = []

    def job(i: int) -> SubmapJobResult:
        if i == 0:
            release.wait(WAIT_S)
        ran.append(i)
        return SubmapJobResult(None, False)

    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    with python_sigint():
        timer.start()
        start = time.perf_counter()
        with pytest.raises(KeyboardInterrupt):
            for i in range(100):  # the queue holds 32: submit blocks long before the end
                executor.submit_frame(job, i, closes=False)
    assert time.perf_counter() - start < WAIT_S
    release.set()
    executor.abort()
    assert ran == [0]
    assert not any(t.name.startswith("submap-worker") for t in threading.enumerate())


def _snapshot(submap_id: int) -> GraphSnapshot:
    anchors = {i: np.diag([1.0, 1.0, 1.0, 1.0]) + i for i in range(submap_id + 1)}
    return GraphSnapshot(anchors, [], {}, submap_id, False)


@pytest.mark.parametrize("threaded", [True, False])
def test_the_view_takes_each_closed_submaps_snapshot_at_the_next_close(threaded: bool) -> None:
    executor = Executor(threaded=threaded)

    def close(submap_id: int) -> SubmapJobResult:
        time.sleep(0.01)  # a threaded worker lags behind the main thread
        return SubmapJobResult(_snapshot(submap_id), False)

    seen = []
    for submap_id in range(4):
        executor.submit_frame(lambda: SubmapJobResult(None, False), closes=False)
        executor.submit_frame(close, submap_id, closes=True)
        seen.append(sorted(executor.view.anchors))
    # the snapshot of the k-th close is applied at close k + 1, whatever the timing
    assert seen == [[], [0], [0, 1], [0, 1, 2]]
    executor.close_submap_worker()
    assert sorted(executor.view.anchors) == [0, 1, 2, 3]
    executor.close_map_worker()


def test_timings_are_booked_per_thread_and_merged_once_the_workers_stopped() -> None:
    executor = Executor(threaded=True)
    threads: dict[str, set[str]] = {"keyframing": set(), "mapping": set()}

    def map_job() -> None:
        threads["mapping"].add(threading.current_thread().name)
        executor.map_timings.book("mapping", clock())

    def frame_job() -> SubmapJobResult:
        threads["keyframing"].add(threading.current_thread().name)
        executor.submap_timings.book("keyframing", clock())
        executor.submit_map_job(map_job)
        return SubmapJobResult(None, False)

    for _ in range(5):
        executor.main_timings.book("odometry", clock())
        executor.submit_frame(frame_job, closes=False)
    assert executor.timings()[0]["keyframing"] == []  # the workers' books are theirs until then
    executor.close_submap_worker()
    executor.close_map_worker()
    wall_s, cpu_s = executor.timings()
    assert [len(wall_s[name]) for name in ("odometry", "keyframing", "mapping")] == [5, 5, 5]
    # each submission and each close
    assert len(wall_s["map_worker_wait"]) == len(wall_s["submap_worker_wait"]) == 6
    assert set(cpu_s) >= {"odometry", "keyframing", "mapping"}
    (keyframing,), (mapping,) = threads["keyframing"], threads["mapping"]
    assert keyframing.startswith("submap-worker") and mapping.startswith("map-worker")


class _SlowMeshMap:
    """Stands in for the neural map: a mesh takes 10 ms, voxel centres nothing."""

    def __init__(self, num_voxels: int = 3) -> None:
        self.meshes = 0
        self.num_voxels = num_voxels

    def extract_mesh(self) -> str:
        time.sleep(0.01)
        self.meshes += 1
        return f"mesh {self.meshes}"

    def voxel_centers(self) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros((3, 3)), np.ones(3)


def test_meshes_for_the_viewer_stay_within_their_share_of_the_time() -> None:
    executor = Executor(threaded=False)
    executor.request_map_snapshots(MapSnapshotRequest(1, False, mesh_time_share=0.2))
    neural_map = _SlowMeshMap()
    start = time.perf_counter()
    for _ in range(40):
        time.sleep(0.005)  # the map job's own work
        executor.publish_map(neural_map, None)
    elapsed = time.perf_counter() - start
    snapshot = executor.latest_map()
    assert snapshot is not None and snapshot.job == 40
    assert 1 <= neural_map.meshes < 40  # every job asked for one
    assert neural_map.meshes * 0.01 <= 0.2 * elapsed + 0.011  # the last one may overrun
    assert snapshot.mesh == f"mesh {neural_map.meshes}" and snapshot.mesh_job <= 40


def test_a_first_mesh_the_share_cannot_pay_for_is_not_extracted() -> None:
    """Before any mesh was timed, its cost is predicted from the map's size: a map whose first
    mesh would take longer than the time share so far gets none (the map still is published)."""
    executor = Executor(threaded=False)
    executor.request_map_snapshots(MapSnapshotRequest(1, False, mesh_time_share=0.2))
    large = _SlowMeshMap(num_voxels=4000)  # predicted 1 s: more than 0.2 of the 0.2 s below
    for _ in range(40):
        time.sleep(0.005)
        executor.publish_map(large, None)
    snapshot = executor.latest_map()
    assert large.meshes == 0 and snapshot is not None and snapshot.mesh is None
