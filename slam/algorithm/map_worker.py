"""Map work (encode, fuse, remap) on one worker thread, in submission order.

The pipeline's main thread runs odometry, keyframing, loop detection and the pose graph; every
change to the neural map is submitted here as a job. Jobs run one at a time in the order they
were submitted and take every pose they need as an argument (a snapshot taken by the main thread
at submission), so the map is the same whatever the timing: threaded or inline, a run gives the
same poses, loops and map. torch, KISS-ICP and numpy's large operations release the GIL, so on
two cores the map work overlaps with the odometry of the next frames.

An exception in a job is raised again by the next :meth:`MapWorker.submit` or
:meth:`MapWorker.drain`, so a failed map update ends the run.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any


class MapWorker:
    """Runs callables in order on one thread (``threaded``) or at once in the caller's thread.

    Args:
        threaded: use a worker thread; False runs each job inside :meth:`submit`.
        max_pending: :meth:`submit` waits while this many jobs are queued or running, so the
            submaps waiting for the worker (and their points) stay bounded.
    """

    def __init__(self, threaded: bool, max_pending: int = 2) -> None:
        self.threaded = threaded
        self.max_pending = max(1, max_pending)
        self._pool = (
            ThreadPoolExecutor(max_workers=1, thread_name_prefix="map-worker") if threaded else None
        )
        self._pending: deque[Future] = deque()
        self.cpu_s: float | None = None  # CPU seconds of the worker thread, set by close()

    def submit(self, job: Callable[..., Any], *args: Any) -> None:
        """Queue ``job(*args)`` after every job submitted before it."""
        if self._pool is None:
            job(*args)
            return
        while self._pending and (self._pending[0].done() or len(self._pending) >= self.max_pending):
            self._pending.popleft().result()  # re-raises a failed job
        self._pending.append(self._pool.submit(job, *args))

    def drain(self) -> None:
        """Wait until every submitted job has run (re-raises the first failure)."""
        while self._pending:
            self._pending.popleft().result()

    def close(self) -> None:
        """Finish the queued jobs and stop the thread."""
        try:
            self.drain()
        finally:
            if self._pool is not None:
                self.cpu_s = self._pool.submit(time.thread_time).result()
                self._pool.shutdown(wait=True)
                self._pool = None
