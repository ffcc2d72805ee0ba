"""Trajectory metrics: ATE after SE(3) alignment, RPE, and the KITTI relative error.

All poses are (N, 4, 4) float64 ``T_W_S`` arrays with frame ``i`` of the estimate corresponding to
frame ``i`` of the ground truth.

- :func:`ate_rmse` and :func:`ate_rotation_rmse_deg` are KISS-ICP's
  ``kiss_icp.metrics.absolute_trajectory_error`` (as evo's ``evo_ape --align``): positions are
  aligned with Umeyama's method without scale (rotation + translation), then the RMSE of the
  position differences (and of the orientation angles) is taken; KISS-ICP returns them as
  float32 (relative precision ~1e-7).
- :func:`align_se3` is the same alignment, returned: KISS-ICP computes it but does not expose it,
  and :func:`ate_per_axis_rmse` (the ATE split into x, y and z) and the plots need it.
- :func:`unaligned_error` is what alignment hides: both trajectories re-expressed relative to
  their first pose (the frame a run's output files claim: the first pose is the identity), the
  position RMSE and the mean heading (yaw) and tilt errors, with no alignment. An attitude offset
  that appears early and stays costs ATE little but puts every later pose off in that frame.
- :func:`kitti_relative_error` follows the KITTI odometry devkit like
  ``kiss_icp.metrics.sequence_error``: segments of 100, 200, ..., 800 m of ground-truth path
  length starting every 10th frame; the error of each segment's relative motion is divided by
  the segment length and averaged. A trajectory shorter than the shortest segment has no
  segment: the result is then ``nan`` (and a warning is logged); pass shorter ``lengths_m`` for
  short indoor sequences and say so when reporting the number.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from common.geometry import rotation_angle_rad

logger = logging.getLogger(__name__)

KITTI_LENGTHS_M: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
LIDAR_UP = (0.0, 0.0, 1.0)
"""The up axis of a LiDAR's frame (x forward, z up)."""
CAMERA_UP = (0.0, -1.0, 0.0)
"""The up axis of a camera's frame (x right, y down, z forward)."""


def _check_pair(est: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    est = np.asarray(est, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if est.ndim != 3 or est.shape[1:] != (4, 4) or gt.shape != est.shape:
        raise ValueError(
            f"trajectory metrics need two (N, 4, 4) pose arrays of equal length; got "
            f"{est.shape} and {gt.shape}"
        )
    if len(est) == 0:
        raise ValueError("trajectory metrics need at least one pose")
    return est, gt


def umeyama_alignment(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rigid transform (4x4, no scale) minimising ``sum |T source_i - target_i|^2``.

    Ours because KISS-ICP's ATE computes it (Eigen's ``umeyama``) without returning it, and
    scipy's ``Rotation.align_vectors`` rejects a trajectory that stands still.
    ``source`` and ``target`` are (N, 3) corresponding points. Umeyama (1991), with the
    reflection fix; degenerate inputs (N < 3 or collinear points) still give a proper rotation,
    though not a unique one.
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    cov = (target - mu_t).T @ (source - mu_s) / len(source)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    T = np.eye(4)
    T[:3, :3] = U @ S @ Vt
    T[:3, 3] = mu_t - T[:3, :3] @ mu_s
    return T


def align_se3(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``T_gt_est`` (4x4): the rigid transform that best maps estimated positions onto the ground
    truth (Umeyama, no scale). Apply it as ``T_gt_est @ est``."""
    est, gt = _check_pair(est, gt)
    return umeyama_alignment(est[:, :3, 3], gt[:, :3, 3])


def _kiss_icp_ate(est: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """``(rotation RMSE rad, translation RMSE m)`` after alignment, from KISS-ICP."""
    from kiss_icp.metrics import absolute_trajectory_error

    rotation_rad, translation_m = absolute_trajectory_error(list(gt), list(est))
    return float(rotation_rad), float(translation_m)


def ate_rmse(est: np.ndarray, gt: np.ndarray, *, align: bool = True) -> float:
    """Absolute trajectory error: RMSE (metres) of position differences after SE(3) alignment.

    With ``align=False`` the trajectories are compared as given (both start at their own W).
    """
    est, gt = _check_pair(est, gt)
    if align:
        return _kiss_icp_ate(est, gt)[1]
    return float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=1))))


def ate_per_axis_rmse(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(3,) RMSE (metres) of the x, y and z position differences after the same alignment as ATE.

    The axes are the ground truth's world axes (z up for KITTI's LiDAR frame and the generated
    LiDAR street), so the last entry is the vertical error; their squares sum to ATE squared.
    """
    est, gt = _check_pair(est, gt)
    est = align_se3(est, gt) @ est
    return np.sqrt(np.mean((est[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=0))


def ate_rotation_rmse_deg(est: np.ndarray, gt: np.ndarray) -> float:
    """RMSE (degrees) of the absolute orientation error after the same alignment as ATE."""
    est, gt = _check_pair(est, gt)
    return float(np.degrees(_kiss_icp_ate(est, gt)[0]))


@dataclass(frozen=True)
class RelativePoseError:
    """RPE over frame pairs ``(i, i + delta)``.

    Attributes:
        trans_rmse_m: RMSE of the translation error of the relative motion (metres).
        rot_rmse_deg: RMSE of its rotation angle error (degrees).
        delta: frame offset.
        num_pairs: number of pairs evaluated (0 gives nan errors).
    """

    trans_rmse_m: float
    rot_rmse_deg: float
    delta: int
    num_pairs: int


def rpe(est: np.ndarray, gt: np.ndarray, delta: int = 1) -> RelativePoseError:
    """Relative pose error between frames ``delta`` apart (evo's ``evo_rpe`` definition:
    ``E_i = (gt_i^-1 gt_{i+d})^-1 (est_i^-1 est_{i+d})``). Alignment does not change it."""
    est, gt = _check_pair(est, gt)
    if delta < 1:
        raise ValueError(f"rpe: delta must be >= 1, got {delta}")
    n = len(est) - delta
    if n <= 0:
        return RelativePoseError(math.nan, math.nan, delta, 0)
    rel_est = np.linalg.inv(est[:-delta]) @ est[delta:]
    rel_gt = np.linalg.inv(gt[:-delta]) @ gt[delta:]
    err = np.linalg.inv(rel_gt) @ rel_est
    t = np.sqrt(np.mean(np.sum(err[:, :3, 3] ** 2, axis=1)))
    r = np.degrees(np.sqrt(np.mean(rotation_angle_rad(err[:, :3, :3]) ** 2)))
    return RelativePoseError(float(t), float(r), delta, n)


def kitti_lengths_within(gt_poses: np.ndarray) -> list[float]:
    """The KITTI segment lengths a ground-truth path is long enough for.

    A path shorter than 100 m keeps ``[100.0]``, for which the error is reported as nan.
    """
    path_m = trajectory_length_m(gt_poses)
    return [length for length in KITTI_LENGTHS_M if length <= path_m] or [min(KITTI_LENGTHS_M)]


def trajectory_length_m(poses: np.ndarray) -> float:
    """Path length (metres) of the positions of ``poses`` (N, 4, 4)."""
    poses = np.asarray(poses, dtype=np.float64)
    if len(poses) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def kitti_relative_error(
    est: np.ndarray,
    gt: np.ndarray,
    *,
    lengths_m: Sequence[float] = KITTI_LENGTHS_M,
    step_frames: int = 10,
) -> tuple[float, float]:
    """KITTI devkit relative error: (translation error %, rotation error deg / 100 m).

    Differs from ``kiss_icp.metrics.sequence_error`` on purpose: any ``lengths_m`` (KISS-ICP fixes
    100-800 m, so short sequences get no number), exact degrees (KISS-ICP uses ``180 / 3.14``), and
    deg / 100 m like the KITTI leaderboard (KISS-ICP: deg / m).

    Averages over every segment that starts at a multiple of ``step_frames`` and spans a
    ground-truth path length of ``lengths_m``: the segment ends at the first frame whose
    distance from the start exceeds the length. Returns ``(nan, nan)`` with a warning when no
    segment fits (trajectory shorter than ``min(lengths_m)``).
    """
    est, gt = _check_pair(est, gt)
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))])
    starts = np.arange(0, len(gt), step_frames)
    t_errs: list[np.ndarray] = []
    r_errs: list[np.ndarray] = []
    for length in lengths_m:
        # First frame j with dist[j] > dist[start] + length.
        ends = np.searchsorted(dist, dist[starts] + length, side="right")
        valid = ends < len(gt)
        if not valid.any():
            continue
        first, last = starts[valid], ends[valid]
        delta_gt = np.linalg.inv(gt[first]) @ gt[last]
        delta_est = np.linalg.inv(est[first]) @ est[last]
        err = np.linalg.inv(delta_est) @ delta_gt
        t_errs.append(np.linalg.norm(err[:, :3, 3], axis=1) / length)
        r_errs.append(rotation_angle_rad(err[:, :3, :3]) / length)
    if not t_errs:
        logger.warning(
            "kitti_relative_error: trajectory of %.1f m is shorter than the shortest segment "
            "(%.1f m); returning nan",
            dist[-1],
            min(lengths_m),
        )
        return math.nan, math.nan
    t_err = float(np.mean(np.concatenate(t_errs)) * 100.0)
    r_err = float(np.degrees(np.mean(np.concatenate(r_errs))) * 100.0)
    return t_err, r_err


@dataclass(frozen=True)
class UnalignedError:
    """:func:`unaligned_error`'s numbers.

    Attributes:
        position_rmse_m: RMSE of the positions in the first pose's frame.
        yaw_mean_abs_deg: mean absolute heading error (rotation about the up axis).
        tilt_mean_deg: mean angle between the estimated and the true up axis.
    """

    position_rmse_m: float
    yaw_mean_abs_deg: float
    tilt_mean_deg: float


def unaligned_error(
    est: np.ndarray, gt: np.ndarray, up: Sequence[float] = LIDAR_UP
) -> UnalignedError:
    """Position, heading and tilt errors with both trajectories expressed relative to their
    first pose and no alignment. ``up``: the up axis in the sensor's frame (:data:`LIDAR_UP`,
    :data:`CAMERA_UP`). The orientation error is the world-frame ``R_est R_gt^T``: its tilt is
    how far it turns the up axis, its yaw how far it turns a horizontal direction about it."""
    est, gt = _check_pair(est, gt)
    est = np.linalg.inv(est[0]) @ est
    gt = np.linalg.inv(gt[0]) @ gt
    position = est[:, :3, 3] - gt[:, :3, 3]
    error = est[:, :3, :3] @ np.swapaxes(gt[:, :3, :3], 1, 2)
    up_axis = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    turned_up = error @ up_axis
    tilt = np.arctan2(np.linalg.norm(np.cross(up_axis, turned_up), axis=1), turned_up @ up_axis)
    horizontal = np.cross(up_axis, [1.0, 0.0, 0.0] if abs(up_axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    horizontal /= np.linalg.norm(horizontal)
    turned = error @ horizontal
    yaw = np.arctan2(np.cross(horizontal, turned) @ up_axis, turned @ horizontal)
    return UnalignedError(
        position_rmse_m=float(np.sqrt(np.mean(np.sum(position**2, axis=1)))),
        yaw_mean_abs_deg=float(np.degrees(np.mean(np.abs(yaw)))),
        tilt_mean_deg=float(np.degrees(np.mean(tilt))),
    )


@dataclass(frozen=True)
class TrajectoryMetrics:
    """The trajectory numbers a run reports (see the module docstring for definitions).

    Attributes:
        ate_rmse_m: ATE RMSE after SE(3) alignment.
        ate_rot_rmse_deg: orientation RMSE after the same alignment.
        ate_x_rmse_m, ate_y_rmse_m, ate_z_rmse_m: ATE per world axis (z: vertical for LiDAR).
        rpe_trans_rmse_m: RPE translation RMSE for consecutive frames.
        rpe_rot_rmse_deg: RPE rotation RMSE for consecutive frames.
        kitti_t_err_percent: KITTI relative translation error (nan when too short).
        kitti_r_err_deg_per_100m: KITTI relative rotation error (nan when too short).
        unaligned_rmse_m, unaligned_yaw_mean_abs_deg, unaligned_tilt_mean_deg:
            :func:`unaligned_error`, in the frame the run's output files claim.
        kitti_lengths_m: segment lengths used for the KITTI error.
        length_m: ground-truth path length.
        num_poses: number of poses compared.
    """

    ate_rmse_m: float
    ate_rot_rmse_deg: float
    ate_x_rmse_m: float
    ate_y_rmse_m: float
    ate_z_rmse_m: float
    rpe_trans_rmse_m: float
    rpe_rot_rmse_deg: float
    kitti_t_err_percent: float
    kitti_r_err_deg_per_100m: float
    unaligned_rmse_m: float
    unaligned_yaw_mean_abs_deg: float
    unaligned_tilt_mean_deg: float
    kitti_lengths_m: tuple[float, ...]
    length_m: float
    num_poses: int

    def as_dict(self) -> dict[str, float | int | list[float]]:
        """Plain dict (for ``metrics.json``)."""
        d = asdict(self)
        d["kitti_lengths_m"] = list(self.kitti_lengths_m)
        return d


def trajectory_metrics(
    est: np.ndarray,
    gt: np.ndarray,
    *,
    kitti_lengths_m: Sequence[float] = KITTI_LENGTHS_M,
    up: Sequence[float] = LIDAR_UP,
) -> TrajectoryMetrics:
    """All of :func:`ate_rmse`, :func:`rpe` (delta 1), :func:`kitti_relative_error` and
    :func:`unaligned_error` (about ``up``) at once."""
    est, gt = _check_pair(est, gt)
    unaligned = unaligned_error(est, gt, up)
    relative = rpe(est, gt, 1)
    t_err, r_err = kitti_relative_error(est, gt, lengths_m=kitti_lengths_m)
    per_axis = ate_per_axis_rmse(est, gt)
    ate_rotation_rad, ate_translation_m = _kiss_icp_ate(est, gt)
    return TrajectoryMetrics(
        ate_rmse_m=ate_translation_m,
        ate_rot_rmse_deg=float(np.degrees(ate_rotation_rad)),
        ate_x_rmse_m=float(per_axis[0]),
        ate_y_rmse_m=float(per_axis[1]),
        ate_z_rmse_m=float(per_axis[2]),
        rpe_trans_rmse_m=relative.trans_rmse_m,
        rpe_rot_rmse_deg=relative.rot_rmse_deg,
        kitti_t_err_percent=t_err,
        kitti_r_err_deg_per_100m=r_err,
        unaligned_rmse_m=unaligned.position_rmse_m,
        unaligned_yaw_mean_abs_deg=unaligned.yaw_mean_abs_deg,
        unaligned_tilt_mean_deg=unaligned.tilt_mean_deg,
        kitti_lengths_m=tuple(float(x) for x in kitti_lengths_m),
        length_m=trajectory_length_m(gt),
        num_poses=len(gt),
    )
