"""Ordered work off the main thread: jobs run on one worker thread, in submission order.

The pipeline has two of them: the *submap worker* (keyframing, normals, loop detection and the
pose graph) and the *map worker* (encode, fuse, remap), so its main thread runs little but the
odometry. Jobs run one at a time in the order they were submitted and take every pose they need
as an argument (a snapshot taken at submission), so the results are the same whatever the
timing: threaded or inline, a run gives the same poses, loops and map. Torch and numpy's large
operations release the GIL, so on two cores the workers overlap with the odometry of the next
frames; KISS-ICP's bindings do not (they hold it through a registration), which is why it runs
in a child process (:mod:`frontends.odometry.child_process`).

An exception in a job is raised again by the next :meth:`MapWorker.submit` or
:meth:`MapWorker.drain`, so a failed map update ends the run. :meth:`MapWorker.cancel` stops a
worker without running its queue (an interrupted run), waiting only for the job it is running.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import Any

SIGNAL_CHECK_S = 0.2
"""A thread waiting for a job wakes this often, so that a signal (Ctrl-C, SIGTERM) that the
kernel handed to another thread still reaches the main thread's handler within this time."""


def job_result(future: Future) -> Any:
    """The job's result (its exception raised), waited for in slices of
    :data:`SIGNAL_CHECK_S`."""
    while not wait([future], timeout=SIGNAL_CHECK_S).done:
        pass
    return future.result()


class MapWorker:
    """Runs callables in order on one thread (``threaded``) or at once in the caller's thread.

    Args:
        threaded: use a worker thread; False runs each job inside :meth:`submit`.
        max_pending: :meth:`submit` waits while this many jobs are queued or running, so the
            submaps waiting for the worker (and their points) stay bounded.
    """

    def __init__(self, threaded: bool, max_pending: int = 2, name: str = "map-worker") -> None:
        self.threaded = threaded
        self.max_pending = max(1, max_pending)
        self._pool = (
            ThreadPoolExecutor(max_workers=1, thread_name_prefix=name) if threaded else None
        )
        self._pending: deque[Future] = deque()
        self.cpu_s: float | None = None  # CPU seconds of the worker thread, set by close()

    def submit(self, job: Callable[..., Any], *args: Any) -> Future:
        """Queue ``job(*args)`` after every job submitted before it; returns its future (done
        already when not ``threaded``: the job ran inside this call, and its exception, if any,
        was raised here)."""
        if self._pool is None:
            done: Future = Future()
            done.set_result(job(*args))
            return done
        while self._pending and (self._pending[0].done() or len(self._pending) >= self.max_pending):
            job_result(self._pending.popleft())  # re-raises a failed job
        future = self._pool.submit(job, *args)
        self._pending.append(future)
        return future

    def drain(self) -> None:
        """Wait until every submitted job has run (re-raises the first failure)."""
        while self._pending:
            job_result(self._pending.popleft())

    def cancel(self) -> None:
        """Drop the queued jobs, wait for the running one and stop the thread; errors of jobs
        are not raised (the run is ending for another reason)."""
        self._pending.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def close(self) -> None:
        """Finish the queued jobs and stop the thread."""
        try:
            self.drain()
        finally:
            if self._pool is not None:
                self.cpu_s = self._pool.submit(time.thread_time).result()
                self._pool.shutdown(wait=True)
                self._pool = None
