"""Trajectory files in the KITTI and TUM formats (readable unchanged by evo and the KITTI devkit).

- KITTI: one pose per line, the first 3 rows of ``T_W_S`` row-major (12 values), no timestamps.
- TUM: ``timestamp tx ty tz qx qy qz qw`` per line (Hamilton quaternion, scalar last); lines
  starting with ``#`` are comments.

Writers are atomic (temporary file in the same folder, then ``os.replace``). Readers raise
:class:`~frontends.errors.DatasetError` with a one-line message naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from common.atomic_io import write_text_atomic
from frontends.errors import DatasetError


def _as_poses(poses: np.ndarray, what: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{what}: poses must be (N, 4, 4), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise ValueError(f"{what}: poses contain nan or inf")
    return poses


def _load_rows(path: Path, num_values: int, layout: str) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"{path}: trajectory file not found; check the path")
    rows = []
    with path.open() as f:
        for line_number, line in enumerate(f, start=1):
            stripped = line.strip()
            if not stripped or stripped.startswith("#"):
                continue
            parts = stripped.replace(",", " ").split()
            try:
                values = [float(v) for v in parts]
            except ValueError:
                values = []
            if len(values) != num_values:
                raise DatasetError(
                    f"{path}:{line_number}: expected {num_values} numbers ({layout}), "
                    f"got '{stripped[:60]}'; fix or remove this line"
                )
            rows.append(values)
    if not rows:
        raise DatasetError(f"{path}: no poses in file; expected lines of {layout}")
    return np.asarray(rows, dtype=np.float64)


def write_kitti(path: str | os.PathLike, poses: np.ndarray) -> None:
    """Write (N, 4, 4) poses as KITTI lines of 12 values."""
    poses = _as_poses(poses, f"write_kitti({path})")
    lines = [" ".join(f"{v:.10g}" for v in T[:3, :].reshape(-1)) for T in poses]
    write_text_atomic(Path(path), "\n".join(lines) + "\n")


def read_kitti(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI pose file into (N, 4, 4) float64."""
    rows = _load_rows(Path(path), 12, "the 12 values of a 3x4 pose")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return poses


def write_tum(path: str | os.PathLike, poses: np.ndarray, timestamps: np.ndarray) -> None:
    """Write (N, 4, 4) poses with (N,) timestamps (seconds) as TUM lines."""
    from scipy.spatial.transform import Rotation

    poses = _as_poses(poses, f"write_tum({path})")
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if len(timestamps) != len(poses):
        raise ValueError(f"write_tum({path}): {len(timestamps)} timestamps for {len(poses)} poses")
    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x, y, z, w
    lines = [
        f"{t:.9f} " + " ".join(f"{v:.10g}" for v in (*T[:3, 3], *q))
        for t, T, q in zip(timestamps, poses, quats, strict=True)
    ]
    write_text_atomic(Path(path), "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: ``(timestamps (N,), poses (N, 4, 4))``."""
    from scipy.spatial.transform import Rotation

    path = Path(path)
    rows = _load_rows(path, 8, "t tx ty tz qx qy qz qw")
    norms = np.linalg.norm(rows[:, 4:8], axis=1)
    if np.any(norms < 1e-6):
        bad = int(np.argmax(norms < 1e-6))
        raise DatasetError(f"{path}: pose {bad} has a zero quaternion; fix the file")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(rows[:, 4:8]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0].copy(), poses
