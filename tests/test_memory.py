"""Freed memory goes back to the OS (slam/algorithm/memory.py)."""

from __future__ import annotations

import ctypes.util
import sys

import numpy as np
import pytest

from slam.algorithm.memory import LARGE_ALLOCATION_BYTES, keep_large_allocations_apart


def _rss_bytes() -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


@pytest.mark.skipif(
    not sys.platform.startswith("linux") or ctypes.util.find_library("c") is None,
    reason="glibc's mallopt and /proc are Linux-only",
)
def test_large_blocks_freed_between_small_live_ones_leave_the_resident_set() -> None:
    """Large arrays allocated between small ones that stay alive (the pattern that pins an
    arena's pages under glibc's growing mmap threshold) leave the RSS as soon as they are
    freed."""
    if not keep_large_allocations_apart():
        pytest.skip("not glibc")
    size = LARGE_ALLOCATION_BYTES + (2 << 20)
    large, pins = [], []
    for _ in range(12):
        large.append(np.ones(size // 8))
        pins.append(np.ones(1000))
    before = _rss_bytes()
    large.clear()
    freed = before - _rss_bytes()
    assert freed > 0.8 * 12 * size, f"only {freed / 1e6:.0f} MB of {12 * size / 1e6:.0f} MB"
    assert len(pins) == 12
