"""The run folder's files written behind the run (slam/run_folder/write_behind.py)."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from common.atomic_io import write_text_atomic
from slam.run_folder.write_behind import WriteBehind


def test_writes_run_in_order_and_a_waiting_one_gives_way_to_a_newer(tmp_path: Path):
    path = tmp_path / "poses.txt"
    started, release = threading.Event(), threading.Event()
    written: list[str] = []

    def write(text: str, block: bool = False) -> None:
        if block:
            started.set()
            release.wait(timeout=30)
        write_text_atomic(path, text)
        written.append(text)

    writes = WriteBehind()
    writes.submit(write, "first", True)
    assert started.wait(timeout=30)  # the first write is running: the next ones wait
    writes.submit(write, "second")
    writes.submit(write, "third")
    assert written == []  # the main thread did not wait for the disk
    release.set()
    writes.close()
    assert written == ["first", "third"]
    assert path.read_text() == "third"


def test_a_failed_write_is_raised_on_the_main_thread():
    def write() -> None:
        raise OSError("No space left on device")

    writes = WriteBehind()
    writes.submit(write)
    with pytest.raises(OSError, match="No space left"):
        writes.close()


def test_a_failed_run_finishes_the_waiting_write_without_raising():
    started, release = threading.Event(), threading.Event()
    written: list[str] = []

    def write(text: str) -> None:
        started.set()
        release.wait(timeout=30)
        written.append(text)
        raise OSError("disk gone")

    writes = WriteBehind()
    writes.submit(write, "running")
    assert started.wait(timeout=30)
    writes.submit(write, "waiting")
    threading.Timer(0.2, release.set).start()  # while abandon() waits for the running one
    writes.abandon()  # the newest progress still reaches the disk; raises nothing
    assert written == ["running", "waiting"]
