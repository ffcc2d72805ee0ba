"""Every frame's place in a run: its submap, its pose relative to that submap's anchor
(``T_A_S``), its odometry pose, its timestamp and its ground truth, in processing order.

A frame's SLAM pose is its anchor's current estimate composed with its ``T_A_S``, so the whole
trajectory follows every optimisation. Where the next submap's anchor is known, the frames in
between also follow it (:func:`frame_poses`): the pose graph corrects the odometry only at the
anchors, and a frame rigid on its own anchor keeps the odometry's drift since that anchor (on
the generated KITTI 00 street, a mean tilt of 0.19 deg against 0.13 deg at the anchors). The
track belongs to the pipeline's main thread.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from itertools import pairwise

import numpy as np
from scipy.spatial.transform import Rotation

from common.geometry import so3_exp


def frame_poses(
    frame_submap: np.ndarray,
    frame_T_A_S: np.ndarray,
    T_W_A: Mapping[int, np.ndarray],
    successors: Mapping[int, tuple[int, np.ndarray]],
) -> np.ndarray:
    """(N, 4, 4) frame poses under the anchor estimates ``T_W_A`` (``{submap_id: pose}``).

    ``successors`` maps a submap to the next anchor of its run and the odometry between the two
    anchors, ``{i: (j, T_Ai_Aj)}``. The frames of a submap with a successor in ``T_W_A`` get the
    gap between the successor's estimate and their own anchor's estimate composed with that
    odometry, in proportion to the path travelled from their anchor: the world-frame position
    gap linearly, the rotation gap along its geodesic. The anchor frame itself keeps its anchor's
    pose, and the last frame before the successor comes within one step of it. Frames of the
    other submaps (the last of a run) stay rigid on their anchor.
    """
    frame_submap = np.asarray(frame_submap, dtype=np.int64)
    if len(frame_submap) == 0:
        return np.zeros((0, 4, 4))
    frame_T_A_S = np.asarray(frame_T_A_S, dtype=np.float64)
    poses = np.array([T_W_A[int(s)] for s in frame_submap]) @ frame_T_A_S
    order = np.argsort(frame_submap, kind="stable")
    ids, starts = np.unique(frame_submap[order], return_index=True)
    for submap_id, rows in zip(ids, np.split(order, starts[1:]), strict=True):
        successor = successors.get(int(submap_id))
        if successor is None or successor[0] not in T_W_A:
            continue
        j, T_Ai_Aj = successor
        predicted = T_W_A[int(submap_id)] @ T_Ai_Aj
        position_gap = T_W_A[j][:3, 3] - predicted[:3, 3]
        rotation_gap = Rotation.from_matrix(T_W_A[j][:3, :3] @ predicted[:3, :3].T).as_rotvec()
        path = np.concatenate([frame_T_A_S[rows, :3, 3], T_Ai_Aj[None, :3, 3]])
        travelled = np.concatenate(
            [[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
        )
        if travelled[-1] > 1e-9:
            share = travelled[:-1] / travelled[-1]
        else:  # standing still: by frame count
            share = np.arange(len(rows)) / len(rows)
        poses[rows, :3, 3] += share[:, None] * position_gap
        poses[rows, :3, :3] = so3_exp(share[:, None] * rotation_gap) @ poses[rows, :3, :3]
    return poses


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

    def slam_poses(
        self,
        T_W_A: Mapping[int, np.ndarray],
        follow_next_anchor: bool = True,
        rigid: Collection[int] = (),
    ) -> np.ndarray:
        """(N, 4, 4) poses under the anchor estimates ``T_W_A`` (``{submap_id: pose}``), each
        frame rigid on its anchor or, with ``follow_next_anchor``, as :func:`frame_poses`; the
        frames of the submaps in ``rigid`` stay rigid on their anchor either way."""
        submaps, T_A_S = self.anchors()
        successors = self.successors() if follow_next_anchor else {}
        for submap_id in rigid:
            successors.pop(submap_id, None)
        return frame_poses(submaps, T_A_S, T_W_A, successors)

    def successors(self) -> dict[int, tuple[int, np.ndarray]]:
        """``{i: (j, T_Ai_Aj)}``: each submap's next one and the odometry between their anchors
        (the pose graph's odometry factor between them)."""
        T_W_A_odometry = {
            s: self._odometry[frames[0]] @ np.linalg.inv(self._T_A_S[frames[0]])
            for s, frames in self._frames_of.items()
        }
        order = list(self._frames_of)  # submaps in the order they opened
        return {
            i: (j, np.linalg.inv(T_W_A_odometry[i]) @ T_W_A_odometry[j]) for i, j in pairwise(order)
        }

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
