"""Ground-truth "odometry": the source's own poses, for mapping-only experiments."""

from __future__ import annotations

import numpy as np

from frontends.errors import DatasetError
from frontends.frame import Frame
from frontends.odometry.base import Odometry, OdometryResult, register_odometry


@register_odometry("gt")
class GroundTruthOdometry(Odometry):
    """Returns ``Frame.T_W_S_gt`` expressed relative to the first frame's ground truth, so that
    W is the first sensor frame as for every other odometry."""

    drifts = False

    def __init__(self) -> None:
        self._T_S0_Wgt: np.ndarray | None = None

    def register(self, frame: Frame) -> OdometryResult:
        if frame.T_W_S_gt is None:
            raise DatasetError(
                f"frame {frame.index}: the source has no ground-truth pose; choose another "
                "odometry (kiss-icp or rgbd) or a sequence with ground truth"
            )
        T_Wgt_S = np.asarray(frame.T_W_S_gt, dtype=np.float64)
        if T_Wgt_S.shape != (4, 4) or not np.all(np.isfinite(T_Wgt_S)):
            raise DatasetError(
                f"frame {frame.index}: ground-truth pose is not a finite 4x4 matrix; check the "
                "source's pose file"
            )
        if self._T_S0_Wgt is None:
            self._T_S0_Wgt = np.linalg.inv(T_Wgt_S)
        return OdometryResult(self._T_S0_Wgt @ T_Wgt_S)
