"""Freed memory goes back to the OS (common/memory.py)."""

from __future__ import annotations

import ctypes.util
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Run in a fresh interpreter: threads other tests leave in the test process (and pytest-xdist's
# own) allocate and free memory while the resident set is being measured.
_CHILD = textwrap.dedent(
    """
    import numpy as np
    from common.memory import LARGE_ALLOCATION_BYTES, keep_large_allocations_apart

    def rss_bytes():
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
        raise SystemExit("no VmRSS")

    if not keep_large_allocations_apart():
        print("not-glibc")
        raise SystemExit(0)
    size = LARGE_ALLOCATION_BYTES + (2 << 20)
    # one large block freed first, as in any run: without the fixed threshold glibc now serves
    # blocks of this size from its arena, and freeing them gives nothing back
    warm_up = np.ones(size // 8)
    del warm_up
    large, pins = [], []
    for _ in range(12):
        large.append(np.ones(size // 8))
        pins.append(np.ones(1000))
    before = rss_bytes()
    large.clear()
    print(before - rss_bytes(), 12 * size, len(pins))
    """
)


@pytest.mark.skipif(
    not sys.platform.startswith("linux") or ctypes.util.find_library("c") is None,
    reason="glibc's mallopt and /proc are Linux-only",
)
def test_large_blocks_freed_between_small_live_ones_leave_the_resident_set() -> None:
    """Large arrays allocated between small ones that stay alive (the pattern that pins an
    arena's pages under glibc's growing mmap threshold) leave the RSS as soon as they are
    freed."""
    done = subprocess.run(
        [sys.executable, "-c", _CHILD],
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    if done.stdout.strip() == "not-glibc":
        pytest.skip("not glibc")
    freed, allocated, pins = (int(v) for v in done.stdout.split())
    assert pins == 12
    assert freed > 0.8 * allocated, f"only {freed / 1e6:.0f} MB of {allocated / 1e6:.0f} MB"
