"""The recording's own thread (slam/app/threaded_logger.py): calls in order on one thread, the
pipeline's state read at the call, a bounded queue, errors raised on the caller's thread."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from slam.algorithm.viz import NullLogger
from slam.app.threaded_logger import ThreadedLogger

WAIT_S = 5.0


class _Calls(NullLogger):
    """Records each call with the thread it ran on; ``hold`` keeps calls waiting."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, object, int]] = []
        self.hold = threading.Event()
        self.hold.set()
        self.fail_at: int | None = None
        self.closed_on: int | None = None

    def set_time(self, frame_index, timestamp_s):
        assert self.hold.wait(WAIT_S)
        if frame_index == self.fail_at:
            raise OSError(f"disk full at frame {frame_index}")
        self.calls.append(("set_time", frame_index, threading.get_ident()))

    def log_metrics(self, **scalars):
        self.calls.append(("metrics", scalars, threading.get_ident()))

    def log_map(self, voxel_centers_W, voxel_values, mesh=None):
        self.calls.append(("map", len(voxel_centers_W), threading.get_ident()))

    def close(self):
        self.closed_on = threading.get_ident()


def test_calls_run_in_order_on_one_other_thread_with_the_state_of_the_call():
    inner = _Calls()
    viz = ThreadedLogger(inner)
    state = {"voxels": 3}
    for frame in range(100):
        viz.set_time(frame, 0.1 * frame)
        viz.log_metrics(frame_ms=float(frame))
    viz.log_map_from(lambda: (np.zeros((state["voxels"], 3)), np.ones(state["voxels"]), None))
    state["voxels"] = 7  # changed after the call: the logged map keeps the value of the call
    viz.close()
    names = [(name, value) for name, value, _ in inner.calls]
    expected = [
        item for f in range(100) for item in (("set_time", f), ("metrics", {"frame_ms": f}))
    ]
    assert names == [*expected, ("map", 3)]
    threads = {ident for _, _, ident in inner.calls}
    assert threads == {inner.closed_on} and threading.get_ident() not in threads


def test_a_recording_that_falls_behind_holds_the_caller_at_the_queue_bound():
    inner = _Calls()
    inner.hold.clear()
    viz = ThreadedLogger(inner, max_pending=4)
    made = []

    def caller():
        for frame in range(10):
            viz.set_time(frame, 0.0)
            made.append(frame)

    thread = threading.Thread(target=caller)
    thread.start()
    thread.join(0.5)
    assert thread.is_alive() and len(made) == 4  # the fifth call waits for the first
    inner.hold.set()
    thread.join(WAIT_S)
    viz.close()
    assert made == list(range(10)) and [v for _, v, _ in inner.calls] == list(range(10))


def test_an_error_on_the_thread_is_raised_on_the_caller_and_the_recording_still_closes():
    inner = _Calls()
    inner.fail_at = 2
    viz = ThreadedLogger(inner, max_pending=1)
    viz.set_time(0, 0.0)
    viz.set_time(1, 0.0)
    viz.set_time(2, 0.0)
    with pytest.raises(OSError, match="disk full at frame 2"):
        viz.set_time(3, 0.0)
    viz.close()
    assert inner.closed_on is not None
    with pytest.raises(RuntimeError, match="closed"):
        viz.set_time(4, 0.0)
