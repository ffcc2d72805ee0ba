"""The run folder: every file a run leaves behind, written atomically (temporary file, then
``os.replace``) so that an interrupted run never leaves a half-written file.

Layout::

    config.yaml                       the resolved configuration
    poses_odometry.{kitti,tum}.txt    odometry trajectory
    poses_slam.{kitti,tum}.txt        loop-closed trajectory
    loops.csv                         every loop candidate, accepted or rejected, with the reason
    mesh.ply                          mesh of the final (remapped) neural map
    map.npz (or the map's format)     the neural map with its submap records
    metrics.json                      trajectory / mesh metrics, counts, timing, memory
    recording.rrd                     the Rerun recording (written by the logger)
    run.log                           the log of the run
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import trimesh

from common.atomic_io import atomic_path, write_text_atomic
from common.geometry import rotation_angle_rad
from mapping.map_io import save_map
from slam.algorithm.loops.base import LoopCandidate
from slam.assembly.config import RunConfig, dump_run_config
from slam.run_folder.trajectory_io import write_kitti, write_tum

logger = logging.getLogger(__name__)

LOOP_FIELDS = ("status", "reason", "graph_inlier", "tx", "ty", "tz", "rotation_deg", "scores")
"""The columns every loop row ends with, in ``loops.csv`` of a run and of a merge
(:func:`loop_fields`)."""
LOOP_COLUMNS = ("reference_submap", "query_submap", "detector", *LOOP_FIELDS)


def json_safe(value: Any) -> Any:
    """A copy JSON can hold: non-finite floats as ``None`` (JSON has no nan/inf), numpy scalars
    and arrays as Python numbers and lists, paths as strings."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (np.floating, float)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, Path):
        return str(value)
    return value


def loop_fields(
    accepted: bool, reason: str, graph_inlier: bool | None, T: np.ndarray | None, scores: dict
) -> list[str]:
    """The :data:`LOOP_FIELDS` of a loop: its relative pose ``T`` as ``tx, ty, tz,
    rotation_deg`` (empty without one), its scores as JSON."""
    inlier = "" if graph_inlier is None else str(bool(graph_inlier)).lower()
    pose = ["", "", "", ""]
    if T is not None:
        pose = [f"{v:.4f}" for v in T[:3, 3]] + [f"{np.degrees(rotation_angle_rad(T[:3, :3])):.3f}"]
    text = json.dumps({k: round(float(v), 4) for k, v in scores.items()})
    return ["accepted" if accepted else "rejected", reason, inlier, *pose, text]


def loops_csv(candidates: Sequence[LoopCandidate]) -> str:
    """The loop candidates as CSV text (one row each, header first)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(LOOP_COLUMNS)
    for c in candidates:
        fields = loop_fields(c.accepted, c.reason, c.graph_inlier, c.T_Ai_Aj, c.scores)
        writer.writerow([c.reference_id, c.query_id, c.detector, *fields])
    return buffer.getvalue()


RUN_STATUS_FILE = "run_status.json"
"""Whether the run finished: ``state`` (running, finished, interrupted, terminated, failed),
``frames_done``, ``frames_total`` and, when it stopped early, ``reason``."""
SESSION_FOLDER = "session"
"""Sub-folder of a run that continued a stored map (``--map`` without ``--localise``): the
session's own run folder, beside the merged map in the run folder itself."""


def read_run_status(folder: Path) -> dict[str, Any] | None:
    """The run's status file, or None when the folder has none (written before it existed)."""
    path = Path(folder) / RUN_STATUS_FILE
    if not path.is_file():
        return None
    try:
        status = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        return {"state": "unknown", "reason": f"{RUN_STATUS_FILE} is not valid JSON"}
    return status if isinstance(status, dict) else {"state": "unknown"}


class KittiRows(NamedTuple):
    """Where each processed frame's pose goes in the KITTI files: ``rows[i]`` is the position
    of the i-th processed frame in the sequence, ``count`` the frames read so far."""

    rows: np.ndarray
    count: int


def kitti_rows_filled(poses: np.ndarray, layout: KittiRows | None) -> np.ndarray:
    """One pose per frame read for the KITTI files, which tools compare row by row: ``poses[i]``
    goes to row ``layout.rows[i]``, and a skipped frame's row repeats the pose of the frame
    before it (the first processed frame's for leading skipped frames). ``layout`` None:
    ``poses`` as they are."""
    if layout is None:
        return poses
    rows = np.asarray(layout.rows, dtype=np.int64)
    source = (
        np.searchsorted(rows, np.arange(max(layout.count, int(rows[-1]) + 1)), side="right") - 1
    )
    return np.asarray(poses)[np.maximum(source, 0)]


def _rewrite_in_place(path: Path, text: str) -> bool:
    """Overwrite an existing small file in place, for when the disk is too full for a new one (a
    status stays within the file system block it already holds); whether it worked. Not atomic,
    which is why it is only the fallback."""
    data = text.encode()
    if len(data) > 4096:
        return False
    try:
        fd = os.open(path, os.O_WRONLY)
    except OSError:
        return False
    try:
        os.pwrite(fd, data, 0)
        os.ftruncate(fd, len(data))
        os.fsync(fd)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


class RunOutputs:
    """Writes the files of one run folder."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)

    def path(self, name: str) -> Path:
        return self.folder / name

    @property
    def recording_path(self) -> Path:
        return self.path("recording.rrd")

    def write_config(self, cfg: RunConfig) -> None:
        write_text_atomic(self.path("config.yaml"), dump_run_config(cfg))

    def write_poses(
        self,
        odometry: np.ndarray,
        slam: np.ndarray,
        timestamps: np.ndarray,
        kitti_rows: KittiRows | None = None,
    ) -> None:
        """Both trajectories in KITTI and TUM format. ``kitti_rows``: the KITTI row of each pose
        (its frame's position in the sequence) when frames were skipped (see
        :func:`kitti_rows_filled`); TUM files hold the processed frames only."""
        if len(odometry) == 0:
            return
        write_kitti(self.path("poses_odometry.kitti.txt"), kitti_rows_filled(odometry, kitti_rows))
        write_tum(self.path("poses_odometry.tum.txt"), odometry, timestamps)
        write_kitti(self.path("poses_slam.kitti.txt"), kitti_rows_filled(slam, kitti_rows))
        write_tum(self.path("poses_slam.tum.txt"), slam, timestamps)

    def write_loops(self, candidates: Sequence[LoopCandidate]) -> None:
        write_text_atomic(self.path("loops.csv"), loops_csv(candidates))

    def write_mesh(self, mesh: trimesh.Trimesh) -> Path:
        path = self.path("mesh.ply")
        with atomic_path(path) as tmp:
            mesh.export(tmp, file_type="ply")
        return path

    def write_map(self, neural_map, submaps: Sequence, session=None) -> Path:
        """The neural map with its submaps and the run's session section
        (:class:`~slam.algorithm.merge.session.SessionRecord`, for merging); ``save_map``
        writes atomically."""
        path = self.path("map.npz")
        save_map(neural_map, path, list(submaps), None if session is None else session.to_arrays())
        return path

    def write_status(
        self, state: str, frames_done: int, frames_total: int, reason: str = ""
    ) -> None:
        """The run's state (see :data:`RUN_STATUS_FILE`)."""
        status = {"state": state, "frames_done": frames_done, "frames_total": frames_total}
        if reason:
            status["reason"] = reason
        text = json.dumps(status) + "\n"
        try:
            write_text_atomic(self.path(RUN_STATUS_FILE), text)
        except OSError:
            if not _rewrite_in_place(self.path(RUN_STATUS_FILE), text):
                raise

    def write_ground_truth(
        self, poses: np.ndarray, timestamps: np.ndarray, kitti_rows: KittiRows | None = None
    ) -> None:
        """The ground-truth trajectory (dataset frames), kept for evaluating a later merge;
        ``kitti_rows`` as in :meth:`write_poses`."""
        write_kitti(self.path("poses_gt.kitti.txt"), kitti_rows_filled(poses, kitti_rows))
        write_tum(self.path("poses_gt.tum.txt"), poses, timestamps)

    def write_localisation(self, text: str) -> None:
        """``localisation.csv`` (:mod:`slam.run_folder.localisation`)."""
        from slam.run_folder.localisation import LOCALISATION_FILE

        write_text_atomic(self.path(LOCALISATION_FILE), text)

    def write_metrics(self, metrics: dict[str, Any]) -> None:
        text = json.dumps(json_safe(metrics), indent=2, sort_keys=False) + "\n"
        write_text_atomic(self.path("metrics.json"), text)
