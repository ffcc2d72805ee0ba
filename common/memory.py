"""Give freed heap memory back to the operating system (glibc only; elsewhere a no-op).

numpy and torch temporaries of a map update are freed when the update ends, but glibc keeps the
freed pages of its heaps (one arena per thread: the map worker has its own) mapped, so a long run's
resident size ratchets up with every large temporary. ``malloc_trim(0)`` unmaps free pages at the
top of each arena and inside it; it costs milliseconds, so it runs once per closed submap, before
the final mesh and while meshing (:mod:`mapping.meshing`: every few batches of chunks and after
assembling the mesh). :func:`keep_large_allocations_apart` (called when a pipeline is built) keeps
the large blocks out of the arenas in the first place.

This module is a leaf (standard library only), so ``mapping/`` and ``slam/`` may both use it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def c_library() -> ctypes.CDLL | None:
    """The C library, None where it cannot be loaded; glibc's functions (``malloc_trim``,
    ``mallopt``) are missing from others (musl, macOS, Windows): look them up with ``getattr``."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        return ctypes.CDLL(name)
    except OSError:
        return None


def release_freed_memory() -> None:
    """Return free heap pages to the OS where the C library supports it."""
    trim = getattr(c_library(), "malloc_trim", None)
    if trim is not None:
        trim(0)


M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
LARGE_ALLOCATION_BYTES = 4 << 20
"""Allocations from this size on get their own pages (see :func:`keep_large_allocations_apart`):
above one scan (~3 MB for 128k float64 points), whose buffers are reused frame after frame."""


@functools.cache
def keep_large_allocations_apart() -> bool:
    """Serve allocations of :data:`LARGE_ALLOCATION_BYTES` and more from their own pages (glibc;
    once per process; returns whether it was applied).

    glibc raises its mmap threshold to the largest block freed so far (up to 32 MB), so after
    the first large temporary every submap-sized array comes from an arena and its pages stay
    resident, fragmented, after it is freed: at 1,000 frames of the generated KITTI street,
    ``malloc_trim(0)`` between two frames returned ~100 MB. A fixed threshold gives the pages of
    large blocks back the moment they are freed; the trim threshold is fixed with it, well above
    the scan-sized blocks that are reused every frame.
    """
    mallopt = getattr(c_library(), "mallopt", None)
    if mallopt is None:
        return False
    applied = mallopt(M_MMAP_THRESHOLD, LARGE_ALLOCATION_BYTES)
    applied &= mallopt(M_TRIM_THRESHOLD, 4 * LARGE_ALLOCATION_BYTES)
    return bool(applied)
