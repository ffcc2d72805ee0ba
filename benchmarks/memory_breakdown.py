"""Where a running pipeline's memory is (LiDAR or RGB-D): a per-object breakdown next to the RSS.

:func:`memory_breakdown` sums the bytes of the numpy arrays and torch tensors each part of a
:class:`~slam.algorithm.pipeline.SlamPipeline` holds (walking its attributes, each buffer once);
KISS-ICP's local map counts 24 bytes a point. glibc's free chunks (``mallinfo2``) are the
allocator slack, and ``malloc_trim(0)`` shows how much of the RSS goes back to the OS. The rest
of the RSS is the code and libraries measured before the first frame (``baseline``) and what no
walk reaches (``unattributed``: resident slack, Python objects, C++ containers, the frames in the
submap worker's queue). RGB-D runs add the loop detector's kept keyframes and the odometry's
state.
"""

from __future__ import annotations

import ctypes
import sys
from typing import Any

import numpy as np

from benchmarks.harness.machine import proc_memory_kib
from common.memory import c_library

MB = 1e6


def rss_mb() -> float:
    """Resident memory of this process in MB."""
    return proc_memory_kib().get("VmRSS", float("nan")) * 1024 / MB


class _Mallinfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",
            "keepcost",
        )
    ]


def allocator_free_mb() -> float | None:
    """Bytes glibc holds free in its arenas (``mallinfo2().fordblks``), MB; None elsewhere."""
    libc = c_library()
    if libc is None or not hasattr(libc, "mallinfo2"):
        return None
    libc.mallinfo2.restype = _Mallinfo2
    return libc.mallinfo2().fordblks / MB


def trim_mb() -> float | None:
    """RSS that ``malloc_trim(0)`` gives back now, MB (None without glibc)."""
    libc = c_library()
    if libc is None or not hasattr(libc, "malloc_trim"):
        return None
    before = rss_mb()
    libc.malloc_trim(0)
    return before - rss_mb()


def buffer_bytes(obj: Any, seen: set[int] | None = None, depth: int = 6) -> int:
    """Bytes of the numpy arrays and torch tensors reachable from ``obj`` through attributes,
    dicts, lists and tuples (``depth`` levels), each underlying buffer once."""
    seen = set() if seen is None else seen
    if depth < 0 or obj is None or isinstance(obj, (str, bytes, int, float, bool)):
        return 0
    if isinstance(obj, np.ndarray):
        base = obj
        while isinstance(base.base, np.ndarray):
            base = base.base
        if id(base) in seen:
            return 0
        seen.add(id(base))
        return base.nbytes
    if type(obj).__module__.startswith("torch") and hasattr(obj, "untyped_storage"):
        storage = obj.untyped_storage()
        key = storage.data_ptr()
        if key in seen:
            return 0
        seen.add(key)
        return storage.nbytes()
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    if isinstance(obj, dict):
        items = list(obj.values())
    elif isinstance(obj, (list, tuple, set, frozenset)):
        items = list(obj)
    elif hasattr(obj, "__dict__"):
        items = list(vars(obj).values())
    elif hasattr(obj, "__slots__"):
        items = [getattr(obj, name, None) for name in obj.__slots__]
    else:
        return 0
    return sum(buffer_bytes(item, seen, depth - 1) for item in items)


def kdtree_bytes(tree: Any) -> int:
    """Bytes a ``scipy.spatial.cKDTree`` holds besides the points it was built on (shared when
    they are float64 and C-contiguous): its index array and its nodes (~72 bytes each, about
    ``2 n / leafsize``)."""
    if tree is None:
        return 0
    indices = getattr(tree, "indices", None)
    n = int(getattr(tree, "n", 0))
    leafsize = max(int(getattr(tree, "leafsize", 16)), 1)
    return (0 if indices is None else indices.nbytes) + 72 * (2 * n // leafsize + 1)


def keyframe_bytes(detector: Any, seen: set[int]) -> dict[str, float]:
    """MB of an RGB-D loop detector's kept keyframes, by kind: images (grey + depth), ORB
    features (pixels, descriptors, lifted points), refinement clouds (points, normals, k-d tree),
    and anything else a kept keyframe holds. Empty for detectors without kept keyframes."""
    features = getattr(detector, "_features", None)
    if not isinstance(features, dict):
        return {}
    out = dict.fromkeys(("images", "orb", "cloud", "other"), 0)
    for kf in features.values():
        if hasattr(kf, "__dict__"):
            fields = dict(vars(kf))
        else:
            fields = {name: getattr(kf, name, None) for name in getattr(kf, "__slots__", ())}
        for name in ("gray", "depth", "_depth"):  # the stored images, not a decoded copy
            out["images"] += buffer_bytes(fields.pop(name, None), seen)
        for name in ("pixels", "descriptors", "points_S"):
            out["orb"] += buffer_bytes(fields.pop(name, None), seen)
        cloud = fields.pop("cloud", None)
        if cloud is not None:
            out["cloud"] += buffer_bytes(
                [getattr(cloud, "points", None), getattr(cloud, "normals", None)], seen
            )
            tree = getattr(cloud, "tree", None)
            out["cloud"] += buffer_bytes(getattr(tree, "data", None), seen) + kdtree_bytes(tree)
        out["other"] += buffer_bytes(fields, seen)
    return {f"loop_keyframes_{k}": v / MB for k, v in out.items()}


def _list_of_arrays_bytes(arrays: list) -> int:
    """An (N, 4, 4) pose list's arrays with their Python object headers."""
    return sum(sys.getsizeof(a) for a in arrays if a is not None)


def memory_breakdown(pipeline, baseline_mb: float) -> dict[str, float]:
    """MB held by each part of ``pipeline`` (call between frames), with the RSS, the baseline
    (RSS before the first frame), the allocator's free bytes and the unattributed rest."""
    seen: set[int] = set()
    parts: dict[str, float] = {}
    kiss = getattr(pipeline.odometry, "_kiss", None)
    if kiss is not None:
        parts["kiss_icp_local_map"] = len(kiss.local_map.point_cloud()) * 24 / MB
    detector = pipeline.loop_detector
    parts["loop_clouds"] = buffer_bytes(getattr(detector, "_clouds", {}), seen) / MB
    parts.update(keyframe_bytes(detector, seen))
    open_submap = getattr(pipeline.keyframer, "current", None)
    parts["open_submap_keyframe"] = buffer_bytes(getattr(open_submap, "keyframe", None), seen) / MB
    if kiss is None:
        parts["odometry_state"] = buffer_bytes(pipeline.odometry, seen) / MB
    parts["place_descriptors"] = buffer_bytes(getattr(detector, "descriptors", {}), seen) / MB
    parts["submap_records"] = buffer_bytes(pipeline.records, seen) / MB
    keyframing = (pipeline.keyframer, pipeline.submap_points)
    parts["keyframer_buffers"] = buffer_bytes(keyframing, seen) / MB
    parts["neural_map_submaps"] = buffer_bytes(pipeline.submaps, seen) / MB
    model = getattr(pipeline.map, "model", None)
    if model is not None:
        buffer_bytes(model, seen)  # the network is part of the baseline
    parts["neural_map_store_and_mesh"] = buffer_bytes(pipeline.map, seen) / MB
    frames = pipeline.frames
    poses = (frames._T_A_S, frames._odometry, frames._gt)
    parts["per_frame_poses"] = sum(map(_list_of_arrays_bytes, poses)) / MB
    parts["pose_graph_and_remap_events"] = (
        buffer_bytes(pipeline.graph, seen) + buffer_bytes(pipeline.remapper.events, seen)
    ) / MB
    current = rss_mb()
    free = allocator_free_mb()
    out = {"rss": current, "baseline": baseline_mb, **parts}
    out["allocator_free"] = float("nan") if free is None else free
    out["unattributed"] = current - baseline_mb - sum(parts.values())
    return out
