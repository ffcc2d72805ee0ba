"""Every frame's place in a run: its submap, its pose relative to that submap's anchor
(``T_A_S``), its odometry pose, its timestamp and its ground truth, in processing order.

A frame's SLAM pose is its anchor's current estimate composed with its ``T_A_S``
(:meth:`FrameTrack.slam_poses`), so the whole trajectory follows every optimisation. The track
belongs to the pipeline's main thread.
"""

from __future__ import annotations

import numpy as np


class FrameTrack:
    """The frames processed so far (module docstring)."""

    def __init__(self) -> None:
        self._submap: list[int] = []
        self._T_A_S: list[np.ndarray] = []
        self._odometry: list[np.ndarray] = []
        self._timestamps: list[float] = []
        self._gt: list[np.ndarray | None] = []
        self._frames_of: dict[int, list[int]] = {}

    def add(
        self,
        submap_id: int,
        T_A_S: np.ndarray,
        T_W_S_odometry: np.ndarray,
        timestamp: float,
        T_W_S_gt: np.ndarray | None,
    ) -> None:
        """The next frame: its submap, its pose in that submap's anchor frame, its odometry
        pose, timestamp and ground truth (None where the frame has none)."""
        self._frames_of.setdefault(submap_id, []).append(len(self._submap))
        self._submap.append(submap_id)
        self._T_A_S.append(T_A_S)
        self._odometry.append(T_W_S_odometry)
        self._timestamps.append(float(timestamp))
        self._gt.append(None if T_W_S_gt is None else np.asarray(T_W_S_gt, dtype=np.float64))

    def __len__(self) -> int:
        return len(self._submap)

    def odometry_poses(self) -> np.ndarray:
        """(N, 4, 4) odometry poses."""
        return np.array(self._odometry).reshape(-1, 4, 4)

    def slam_poses(self, T_W_A: dict[int, np.ndarray]) -> np.ndarray:
        """(N, 4, 4) poses under the anchor estimates ``T_W_A`` (``{submap_id: pose}``)."""
        if not self._submap:
            return np.zeros((0, 4, 4))
        anchors = np.array([T_W_A[s] for s in self._submap])
        return anchors @ np.array(self._T_A_S)

    def anchors(self) -> tuple[np.ndarray, np.ndarray]:
        """Every frame's submap id ``(N,)`` and pose in its anchor frame ``T_A_S (N, 4, 4)``."""
        submaps = np.array(self._submap, dtype=np.int64)
        return submaps, np.array(self._T_A_S).reshape(-1, 4, 4)

    def submap_frames(self, submap_id: int) -> list[int]:
        """Indices (processing order) of the frames of a submap."""
        return self._frames_of.get(submap_id, [])

    def submap_frame_counts(self) -> dict[int, int]:
        """Frames of each submap, ``{submap_id: count}``."""
        return {i: len(frames) for i, frames in self._frames_of.items()}

    def timestamps(self) -> np.ndarray:
        return np.array(self._timestamps)

    def gt_poses(self) -> np.ndarray | None:
        """(N, 4, 4) ground truth in its own world frame, or None when any frame lacks it."""
        if not self._gt or any(g is None for g in self._gt):
            return None
        return np.array(self._gt)

    def gt_poses_where_known(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(N, 4, 4) ground truth with NaN rows where a frame has none, and the (N,) mask of the
        frames that have one; None when no frame has ground truth."""
        if not any(g is not None for g in self._gt):
            return None
        mask = np.array([g is not None for g in self._gt])
        poses = np.full((len(self._gt), 4, 4), np.nan)
        poses[mask] = np.array([g for g in self._gt if g is not None])
        return poses, mask
