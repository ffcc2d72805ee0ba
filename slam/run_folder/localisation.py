"""``localisation.csv`` and ``metrics.json``'s ``localisation`` of a run in a stored map.

Every processed frame gets a status: ``anchored`` when its submap's anchor holds a registration to
the stored map that the pose graph keeps (:mod:`slam.algorithm.localisation`), ``odometry``
otherwise (before the first placement, in a stretch the map does not cover, or where no
registration verified); its pose there is the odometry's from the last anchored submap.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from typing import Any

import numpy as np

LOCALISATION_FILE = "localisation.csv"
ANCHORED = "anchored"
ODOMETRY = "odometry"


def frame_statuses(frame_submaps: Sequence[int], anchored: Collection[int]) -> list[str]:
    """The status of each frame from its submap id and the map-anchored submaps."""
    return [ANCHORED if int(s) in anchored else ODOMETRY for s in frame_submaps]


def localisation_csv(
    frames: Sequence[int],
    timestamps: Sequence[float],
    frame_submaps: Sequence[int],
    statuses: Sequence[str],
) -> str:
    """One row per processed frame: its index in the dataset, timestamp, submap and status."""
    rows = ["frame,timestamp,submap,status"]
    for frame, stamp, submap, status in zip(
        frames, timestamps, frame_submaps, statuses, strict=True
    ):
        rows.append(f"{int(frame)},{float(stamp):.6f},{int(submap)},{status}")
    return "\n".join(rows) + "\n"


def _runs(frames: Sequence[int], flags: np.ndarray) -> list[list[int]]:
    """``[first, last]`` frame of each run of consecutive True ``flags``."""
    ranges, start = [], None
    for k, flag in enumerate(flags):
        if flag and start is None:
            start = k
        if not flag and start is not None:
            ranges.append([int(frames[start]), int(frames[k - 1])])
            start = None
    if start is not None:
        ranges.append([int(frames[start]), int(frames[-1])])
    return ranges


def localisation_summary(
    frames: Sequence[int],
    frame_submaps: Sequence[int],
    statuses: Sequence[str],
    placement_submap: int | None,
    placed_at_frame: int | None,
) -> dict[str, Any]:
    """``metrics.json``'s ``localisation``: the fraction of frames anchored, the frames before
    the placing submap, and the coverage gaps after it (frame ranges of odometry-only frames)."""
    n = len(statuses)
    anchored = np.array([s == ANCHORED for s in statuses], dtype=bool)
    submaps = np.asarray(frame_submaps, dtype=np.int64)
    if placement_submap is None:
        before = np.ones(n, dtype=bool)
    else:
        before = submaps < placement_submap
    outside = ~anchored & ~before
    gaps = _runs(frames, outside)
    return {
        "frames": n,
        "frames_anchored": int(anchored.sum()),
        "fraction_anchored": float(anchored.mean()) if n else 0.0,
        "frames_before_placement": int(before.sum()),
        "placed_at_frame": placed_at_frame,
        "coverage_gaps": gaps,
        "frames_in_gaps": int(outside.sum()),
    }
