"""Give freed heap memory back to the operating system (glibc only; elsewhere a no-op).

numpy and torch temporaries of a map update are freed when the update ends, but glibc keeps the
freed pages of its heaps (one arena per thread: the map worker has its own) mapped, so a long run's
resident size ratchets up with every large temporary. ``malloc_trim(0)`` unmaps free pages at the
top of each arena and inside it; it costs milliseconds, so it runs once per closed submap and
before the final mesh.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _malloc_trim():
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        return ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):  # not glibc (musl, macOS, Windows)
        return None


def release_freed_memory() -> None:
    """Return free heap pages to the OS where the C library supports it."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
