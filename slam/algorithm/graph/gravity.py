"""The up direction of a submap from its vertical structure (walls, poles, trunks).

Why: a LiDAR odometry whose scans carry a small beam-elevation error (or whose registration has a
slight pitch bias) drifts with a constant curvature: the trajectory lies on a sphere instead of a
plane. Such a drift integrates to zero around every closed loop, so revisits agree with it and
loop closure cannot see it; the vertical error between revisits stays. What a curved world does
change is the direction of gravity seen from each submap. Walls and poles are vertical, so their
normals are horizontal; the direction most orthogonal to them is the local up, independent of the
road's slope. One such measurement per submap, as a factor on the anchor's tilt
(:meth:`slam.algorithm.graph.pose_graph.PoseGraph.add_gravity`), takes the curvature out.

The measurement is taken on the anchor's own scan, in the anchor frame: a submap's accumulated
cloud carries the odometry's drift within the submap and coarser normals, and was measured to
give a worse estimate (3-5 mrad RMS against 1-2 mrad on generated streets).

The estimate refines a guess of the up direction (the anchor's up in the current graph) by
Gauss-Newton over the tilt, on the normals within a shrinking angle of horizontal. Its information
is the normals' spread around the up axis: walls facing one way only constrain the tilt about one
axis, and the other gets none.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry import so3_exp
from common.normals import estimate_normals
from frontends.frame import Frame, point_ranges_m
from slam.algorithm.graph.config import GravityConfig

_GATES_RAD = (1.0, 0.5, 0.25, 0.125, 0.125, 0.125)
"""Gates on the angle between a normal and the horizontal, one Gauss-Newton step each, as
multiples of ``GravityConfig.max_wall_tilt_rad``: the first pass takes every roughly vertical
surface, the last ones only those that agree with the refined up direction."""


@dataclass(frozen=True)
class UpMeasurement:
    """The up direction seen from a submap anchor.

    Attributes:
        up_A: (3,) unit up direction in the anchor frame.
        information_A: (3, 3) information matrix (1/rad^2) of a small rotation of the anchor
            (anchor-frame rotation vector); rank 2 at most, nothing about the rotation around
            ``up_A`` (the heading).
        num_normals: wall normals the estimate rests on.
    """

    up_A: np.ndarray
    information_A: np.ndarray
    num_normals: int


def _tilt_basis(up: np.ndarray) -> np.ndarray:
    """(3, 2): two unit vectors orthogonal to ``up`` and to each other."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1)], axis=1)


def scan_normals(points_S: np.ndarray, cfg: GravityConfig) -> np.ndarray:
    """Unit normals of one scan (sensor frame), on its points voxelised at ``cfg.voxel_m``
    between ``cfg.min_range_m`` and ``cfg.max_range_m``; rows without a normal are dropped."""
    from kiss_icp.voxelization import voxel_down_sample

    points = np.asarray(points_S, dtype=np.float64)
    ranges = point_ranges_m(points)
    points = points[(ranges >= cfg.min_range_m) & (ranges <= cfg.max_range_m)]
    if len(points) == 0:
        return np.zeros((0, 3))
    points = voxel_down_sample(points, cfg.voxel_m)
    normals, valid = estimate_normals(
        points, np.zeros(3), num_neighbours=cfg.normal_neighbours, max_radius_m=cfg.normal_radius_m
    )
    return normals[valid]


def measure_up(frame: Frame, up_guess_S: np.ndarray, cfg: GravityConfig) -> UpMeasurement | None:
    """The up direction in a frame's sensor frame from its own normals (RGB-D) or from normals
    estimated on its points (:func:`scan_normals`); None where its walls do not give one."""
    normals = frame.normals
    normals = scan_normals(frame.points, cfg) if normals is None else np.asarray(normals)
    return estimate_up(normals, up_guess_S, cfg)


def estimate_up(
    normals_A: np.ndarray, up_guess_A: np.ndarray, cfg: GravityConfig
) -> UpMeasurement | None:
    """Up direction from unit normals (anchor frame), or None when too few surfaces are
    vertical or they do not constrain the tilt.

    ``up_guess_A`` must be within ``cfg.max_wall_tilt_rad`` of the truth for the walls to be
    found (the graph's current estimate is: its tilt error is milliradians).
    """
    normals = np.asarray(normals_A, dtype=np.float64)
    normals = normals[np.linalg.norm(normals, axis=1) > 0.5]
    up = np.asarray(up_guess_A, dtype=np.float64)
    up = up / np.linalg.norm(up)
    for gate in _GATES_RAD:
        wall = np.abs(normals @ up) < np.sin(gate * cfg.max_wall_tilt_rad)
        if int(wall.sum()) < cfg.min_wall_normals:
            return None
        n = normals[wall]
        basis = _tilt_basis(up)
        # d(n . up) / d(omega) for up -> up + omega x up: (up x n) . omega
        jacobian = np.cross(up, n) @ basis
        residual = n @ up
        step = np.linalg.solve(jacobian.T @ jacobian + 1e-9 * np.eye(2), -jacobian.T @ residual)
        up = so3_exp(basis @ step) @ up
        up /= np.linalg.norm(up)
    # Spread of the wall normals around the up axis, normalised so that walls facing every way
    # give the identity on the tilt plane; each axis is capped there, so a thousand walls facing
    # one way are worth no more than one direction's full share.
    basis = _tilt_basis(up)
    final_gate = np.sin(_GATES_RAD[-1] * cfg.max_wall_tilt_rad)
    jacobian = np.cross(up, normals[np.abs(normals @ up) < final_gate]) @ basis
    count = len(jacobian)
    if count < cfg.min_wall_normals:
        return None
    shape = jacobian.T @ jacobian / (count / 2.0)
    values, vectors = np.linalg.eigh(shape)
    values = np.minimum(values, 1.0)
    if values[-1] < cfg.min_spread:
        return None
    values[values < cfg.min_spread] = 0.0
    axes = basis @ vectors
    information = (axes * values) @ axes.T / cfg.sigma_rad**2
    return UpMeasurement(up_A=up, information_A=information, num_normals=count)
