"""Sensor trajectories for generated sequences, as (N, 4, 4) float64 poses T_W_S.

LiDAR sensor frame: x forward, y left, z up. Camera frame: x right, y down, z forward.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from frontends.errors import DatasetError


def _rounded_rectangle(s: np.ndarray, length_m: float, width_m: float, radius_m: float):
    """Point and unit tangent at arc length ``s`` on a counter-clockwise rounded rectangle.

    The rectangle is centred on the origin; ``s = 0`` is the middle of the bottom straight.
    """
    a, b, r = length_m / 2 - radius_m, width_m / 2 - radius_m, radius_m
    quarter = np.pi * r / 2
    pieces = [  # (start point, direction or arc centre, kind, length)
        ("line", np.array([0.0, -b - r]), np.array([1.0, 0.0]), a),
        ("arc", np.array([a, -b]), -np.pi / 2, quarter),
        ("line", np.array([a + r, -b]), np.array([0.0, 1.0]), 2 * b),
        ("arc", np.array([a, b]), 0.0, quarter),
        ("line", np.array([a, b + r]), np.array([-1.0, 0.0]), 2 * a),
        ("arc", np.array([-a, b]), np.pi / 2, quarter),
        ("line", np.array([-a - r, b]), np.array([0.0, -1.0]), 2 * b),
        ("arc", np.array([-a, -b]), np.pi, quarter),
        ("line", np.array([-a, -b - r]), np.array([1.0, 0.0]), a),
    ]
    total = sum(p[3] for p in pieces)
    s = np.mod(s, total)
    xy = np.zeros((len(s), 2))
    tangent = np.zeros((len(s), 2))
    start = 0.0
    for kind, p0, q, length in pieces:
        m = (s >= start) & (s < start + length + 1e-12)
        u = s[m] - start
        if kind == "line":
            xy[m] = p0 + u[:, None] * q
            tangent[m] = q
        else:
            ang = q + u / r
            xy[m] = p0 + r * np.stack([np.cos(ang), np.sin(ang)], 1)
            tangent[m] = np.stack([-np.sin(ang), np.cos(ang)], 1)
        start += length
    return xy, tangent, total


def rounded_rectangle_length(length_m: float, width_m: float, radius_m: float) -> float:
    """Perimeter of the rounded rectangle used by :func:`loop_lidar_trajectory`."""
    return 2 * (length_m - 2 * radius_m) + 2 * (width_m - 2 * radius_m) + 2 * np.pi * radius_m


def loop_lidar_trajectory(
    num_frames: int,
    *,
    block_length_m: float = 60.0,
    block_width_m: float = 40.0,
    corner_radius_m: float = 9.0,
    sensor_height_m: float = 1.73,
) -> np.ndarray:
    """One lap around a block: frames evenly spaced, the frame after the last would be the first.

    Heading follows the road with small smooth yaw/pitch/roll wobbles and a gentle +-0.5 m hill,
    all periodic over the lap so the loop closes smoothly. The default block (perimeter ~186 m)
    gives ~1 m per frame at 186 frames.
    """
    if num_frames < 2:
        raise DatasetError(f"num_frames={num_frames}: a loop needs at least 2 frames")
    perimeter = rounded_rectangle_length(block_length_m, block_width_m, corner_radius_m)
    s = np.arange(num_frames) * perimeter / num_frames
    xy, tangent, _ = _rounded_rectangle(s, block_length_m, block_width_m, corner_radius_m)
    phase = 2 * np.pi * s / perimeter
    z = sensor_height_m + 0.5 * np.sin(phase)
    yaw = np.arctan2(tangent[:, 1], tangent[:, 0]) + np.deg2rad(2.0) * np.sin(3 * phase)
    pitch = np.deg2rad(1.0) * np.sin(2 * phase + 0.5)
    roll = np.deg2rad(0.5) * np.sin(5 * phase + 1.0)
    poses = np.tile(np.eye(4), (num_frames, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], 1)).as_matrix()
    poses[:, :3, 3] = np.column_stack([xy, z])
    return poses


def read_kitti_poses(path: Path) -> np.ndarray:
    """(N, 4, 4) poses from a KITTI poses file (12 values a row)."""
    try:
        values = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as e:
        raise DatasetError(
            f"{path}: cannot read KITTI poses ({e}); pass a KITTI poses/NN.txt"
        ) from e
    if values.shape[1] != 12:
        raise DatasetError(
            f"{path}: expected 12 values per row, got {values.shape[1]}; pass a KITTI poses file"
        )
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :4] = values.reshape(-1, 3, 4)
    return poses


def read_kitti_tr(path: Path) -> np.ndarray:
    """The 4x4 LiDAR-to-camera transform ``Tr`` from a KITTI odometry calib.txt."""
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as e:
        raise DatasetError(
            f"{path}: cannot read KITTI calibration ({e}); pass sequences/NN/calib.txt"
        ) from e
    for line in lines:
        key, _, rest = line.partition(":")
        if key.strip() == "Tr":
            values = np.array(rest.split(), dtype=np.float64)
            if values.size != 12:
                break
            T = np.eye(4)
            T[:3, :4] = values.reshape(3, 4)
            return T
    raise DatasetError(f"{path}: no 'Tr:' line with 12 values; pass a KITTI odometry calib.txt")


def kitti_lidar_trajectory(
    poses_path: Path, calib_path: Path, *, start: int = 0, num_frames: int, step: int = 1
) -> np.ndarray:
    """LiDAR poses T_lidar = inv(Tr) @ T_cam @ Tr of frames ``start, start+step, ...``.

    Poses stay in the KITTI world (the LiDAR frame of the sequence's first frame, z about up).
    """
    T_cam = read_kitti_poses(Path(poses_path))
    Tr = read_kitti_tr(Path(calib_path))
    if step < 1 or start < 0 or num_frames < 1:
        raise DatasetError(f"{poses_path}: need start >= 0, step >= 1, num_frames >= 1")
    stop = start + (num_frames - 1) * step
    if stop >= len(T_cam):
        raise DatasetError(
            f"{poses_path}: window start={start} num_frames={num_frames} step={step} needs frame "
            f"{stop} but the file has {len(T_cam)}; choose a shorter window"
        )
    return np.linalg.inv(Tr) @ T_cam[start : stop + 1 : step] @ Tr


def room_camera_trajectory(
    num_frames: int,
    *,
    radius_m: float = 0.8,
    height_m: float = 1.4,
    target_radius_m: float = 2.0,
    target_height_m: float = 1.0,
    lead_angle_rad: float = np.deg2rad(100.0),
) -> np.ndarray:
    """One lap of a camera circling the room centre, looking across the room, as T_W_C.

    The camera moves counter-clockwise on a circle of ``radius_m`` and looks at a point that
    runs ahead of it on a wider circle, so it sweeps the walls and furniture; height and roll
    wobble smoothly. Frames are evenly spaced; the frame after the last would be the first.
    """
    if num_frames < 2:
        raise DatasetError(f"num_frames={num_frames}: a loop needs at least 2 frames")
    theta = 2 * np.pi * np.arange(num_frames) / num_frames
    eye = np.stack(
        [radius_m * np.cos(theta), radius_m * np.sin(theta), height_m + 0.1 * np.sin(2 * theta)], 1
    )
    ang = theta + lead_angle_rad
    target = np.stack(
        [
            target_radius_m * np.cos(ang),
            target_radius_m * np.sin(ang),
            target_height_m + 0.2 * np.sin(3 * theta),
        ],
        1,
    )
    forward = target - eye
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward], axis=2)  # columns: camera x, y, z in the world
    roll = Rotation.from_rotvec(np.deg2rad(3.0) * np.sin(2 * theta)[:, None] * [0.0, 0.0, 1.0])
    poses = np.tile(np.eye(4), (num_frames, 1, 1))
    poses[:, :3, :3] = R @ roll.as_matrix()
    poses[:, :3, 3] = eye
    return poses
