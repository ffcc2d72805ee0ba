"""The gravity frame in the pose graph: a node ``G`` whose z axis is up (its heading and position
fixed by a prior, its tilt free or held), and factors between ``G`` and an anchor that constrain
only the anchor's tilt, from an up direction measured in the anchor's frame
(:mod:`slam.algorithm.graph.gravity`). Used by the live graph
(:meth:`slam.algorithm.graph.pose_graph.PoseGraph.add_gravity`) and by the merge."""

from __future__ import annotations

import gtsam
import numpy as np

from common.geometry import so3_exp
from slam.algorithm.graph.gravity import UpMeasurement
from slam.algorithm.graph.gtsam_poses import pose3

GRAVITY_KEY = gtsam.symbol("g", 0)
"""Key of the gravity frame ``G`` (never a submap id: those are small integers)."""
_HELD_SIGMA = 1e-6
"""Prior standard deviation (rad, m) of what the gravity frame's prior fixes."""
_FREE_TILT_SIGMA_RAD = 1.0
"""Prior standard deviation of a free gravity-frame tilt (only keeps the problem well posed)."""
_UNCONSTRAINED_INFORMATION = 1e-8
"""Information given to what a gravity factor does not measure (heading, position), so that its
noise model stays positive definite."""


def rotation_onto_z(v: np.ndarray) -> np.ndarray:
    """The smallest rotation that turns the unit vector ``v`` onto ``[0, 0, 1]``."""
    v = np.asarray(v, dtype=np.float64) / np.linalg.norm(v)
    axis = np.cross(v, [0.0, 0.0, 1.0])
    sin = float(np.linalg.norm(axis))
    if sin < 1e-12:
        return np.eye(3) if v[2] > 0 else np.diag([1.0, -1.0, -1.0])
    angle = float(np.arctan2(sin, v[2]))
    return so3_exp(axis / sin * angle)


def gravity_frame_noise(hold_tilt: bool) -> gtsam.noiseModel.Base:
    """Noise of the gravity frame's prior: heading and position fixed (they mean nothing), the
    tilt held where it is (``hold_tilt``) or free."""
    tilt = _HELD_SIGMA if hold_tilt else _FREE_TILT_SIGMA_RAD
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([tilt, tilt, *[_HELD_SIGMA] * 4]))


def gravity_frame_prior(
    key: int, T_W_A: np.ndarray, measurement: UpMeasurement, *, hold_tilt: bool = False
) -> tuple[gtsam.PriorFactorPose3, np.ndarray]:
    """The gravity frame ``G`` at the world origin with its z axis on a first measured up
    direction, and its prior (:func:`gravity_frame_noise`): with ``hold_tilt`` that first
    measurement sets the tilt for good, otherwise the tilt is free."""
    T_W_G = np.eye(4)
    T_W_G[:3, :3] = rotation_onto_z(T_W_A[:3, :3] @ measurement.up_A).T
    noise = gravity_frame_noise(hold_tilt)
    return gtsam.PriorFactorPose3(key, pose3(T_W_G), noise), T_W_G


def gravity_factor(
    key_G: int, key_A: int, T_W_G: np.ndarray, T_W_A: np.ndarray, measurement: UpMeasurement
) -> gtsam.BetweenFactorPose3:
    """A between-factor ``G -> A`` on an anchor's tilt: its measurement turns the current
    ``T_G_A`` minimally so that ``up_A`` maps onto G's z axis, and its noise informs only the
    anchor's tilt (``measurement.information_A``), nothing about its heading or position."""
    T_G_A = np.linalg.inv(T_W_G) @ T_W_A
    measured = T_G_A.copy()
    measured[:3, :3] = rotation_onto_z(T_G_A[:3, :3] @ measurement.up_A) @ T_G_A[:3, :3]
    information = np.eye(6) * _UNCONSTRAINED_INFORMATION
    information[:3, :3] += measurement.information_A
    noise = gtsam.noiseModel.Gaussian.Information(information)
    return gtsam.BetweenFactorPose3(key_G, key_A, pose3(measured), noise)
