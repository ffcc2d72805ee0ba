"""The run folder's files rewritten at each submap close, on a thread of their own.

At each submap close the runner rewrites the trajectories, ``loops.csv``, ``localisation.csv``
and ``run_status.json``: seven atomic writes, each with two ``fsync`` calls, about 10 ms each on
a VM's disk. On the main thread that stalled the odometry at every close (about 85 ms every 12
frames of the generated street, 7 ms a frame against its odometry's 22 ms).
:class:`WriteBehind` runs them on one background thread, in order, from copies the main thread
takes; every file is still written atomically and whole. A write that is still waiting when a
newer one is submitted is dropped (the newer one rewrites the same files), so a slow disk never
queues more than one. An error of a write is raised on the main thread at the next submission
or at :meth:`WriteBehind.close`. A failed run still finishes the queued one, so its folder keeps
the newest progress, but raises no write error (:meth:`WriteBehind.abandon`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any


class WriteBehind:
    """Runs write jobs in submission order on one background thread (module docstring)."""

    def __init__(self) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="run-folder-writes")
        self._pending: deque[Future] = deque()

    def submit(self, write: Callable[..., Any], *args: Any) -> None:
        """Queue ``write(*args)``; a queued write not started yet is dropped (``write`` rewrites
        the same files). Raises the error of a write that failed since the last call."""
        self._collect(wait=False)
        for future in self._pending:
            future.cancel()
        self._pending.append(self._pool.submit(write, *args))

    def close(self) -> None:
        """Wait for every queued write and stop the thread; raises the first write's error."""
        try:
            self._collect(wait=True)
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def abandon(self) -> None:
        """Finish the queued writes and stop the thread, raising none of their errors (the run
        failed already; its own error is the one to report)."""
        self._pool.shutdown(wait=True)
        self._pending.clear()

    def _collect(self, wait: bool) -> None:
        while self._pending and (wait or self._pending[0].done()):
            future = self._pending.popleft()
            if not future.cancelled():
                future.result()
