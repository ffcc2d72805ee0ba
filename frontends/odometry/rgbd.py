"""RGB-D odometry with OpenCV 5 ``cv2.Odometry`` (dense photometric + ICP, RGB_DEPTH).

Direction convention (verified by ``tests/test_odometry.py`` with a rendered known motion):
``compute(src, dst)`` returns ``Rt`` with ``Rt @ p_src = p_dst``, i.e. ``Rt = T_dst_src``. With
``src`` the reference (key)frame and ``dst`` the new frame, the new pose is
``T_W_new = T_W_ref @ inv(Rt)``.

OpenCV 5 offers no initial guess to ``compute`` (it always starts from identity), so each new
frame is registered to a *keyframe* that is replaced once the camera has moved
``keyframe_translation_m`` / ``keyframe_rotation_deg`` away from it. Keyframes must stay close:
starting from identity, OpenCV's estimate degrades quickly with the baseline. Measured on 7-Scenes
redkitchen frames 0-399 (``benchmarks/results/odometry.md``): ATE 3.5 cm with 3 cm / 2 deg
keyframes (the default), 6.2 cm frame-to-frame, 24 cm with 10 cm / 5 deg keyframes.

If registration to the keyframe fails, the previous frame is tried; if that fails too, the pose
is extrapolated with constant velocity, a warning is logged and ``num_failures`` is incremented.

Information: OpenCV does not return the Hessian of its cost, so after each registration the
point-to-plane cost of the frame's points against the reference frame's points and normals is
evaluated at the estimated pose (:func:`~common.point_to_plane.point_to_plane_hessian`,
a few thousand points). ``covariance_factor * sigma^2 H^-1`` of each registration is chained from
keyframe to keyframe (``Ad`` transforms); each result carries the covariance of the motion since
the latest :meth:`RgbdOdometry.restart_covariance`, which the pipeline calls at every new submap
anchor, so the anchor's result weighs the pose graph's odometry edge. A failed registration adds a
large covariance.
"""

from __future__ import annotations

import logging

import numpy as np

from common.geometry import rotation_angle_rad
from common.point_to_plane import adjoint, point_to_plane_hessian
from frontends.errors import DatasetError
from frontends.frame import Frame
from frontends.odometry.base import Odometry, OdometryResult, register_odometry
from frontends.odometry.rgbd_config import RgbdOdometryConfig

__all__ = ["RgbdOdometry", "RgbdOdometryConfig"]

logger = logging.getLogger(__name__)


def _level_values(values: list, dtype: type) -> np.ndarray:
    """Per-pyramid-level values in the shape OpenCV 5.0's setters can read.

    ``OdometrySettings.setIterCounts`` / ``setMinGradientMagnitudes`` take the number of levels
    from the array's width but read level ``i`` from element 0 of row ``i``: a 1-D or row array
    crashes, a column sets only one level. An n x n array with the values in every column works.
    """
    column = np.asarray(values, dtype=dtype).reshape(-1, 1)
    return np.ascontiguousarray(np.tile(column, (1, len(column))))


def _downscale_depth(depth: np.ndarray, factor: int, max_spread_m: float) -> np.ndarray:
    """Average depth over ``factor`` x ``factor`` blocks (aligned with ``cv2.INTER_AREA``).

    A block is invalid (0) when fewer than half of its pixels are valid or its valid depths
    spread more than ``max_spread_m`` (a depth edge: averaging would invent a surface).
    """
    h, w = depth.shape[0] // factor, depth.shape[1] // factor
    # One pass per pixel of the block over strided (h, w) views: about 7x faster than reducing
    # a (h, w, factor^2) copy of the blocks; the same result up to the rounding of the sum.
    total = np.zeros((h, w), np.float32)
    count = np.zeros((h, w), np.int32)
    high = np.full((h, w), -np.inf, np.float32)
    low = np.full((h, w), np.inf, np.float32)
    for i in range(factor):
        for j in range(factor):
            part = depth[i : h * factor : factor, j : w * factor : factor]
            valid = part > 0
            total += np.where(valid, part, 0.0)
            count += valid
            np.maximum(high, np.where(valid, part, -np.inf), out=high)
            np.minimum(low, np.where(valid, part, np.inf), out=low)
    keep = (count * 2 >= factor * factor) & (high - low <= max_spread_m)
    return np.where(keep, total / np.maximum(count, 1), 0.0).astype(np.float32)


def _rotation_deg(T: np.ndarray) -> float:
    return float(np.degrees(rotation_angle_rad(T[:3, :3])))


@register_odometry("rgbd")
class RgbdOdometry(Odometry):
    """Frame-to-keyframe RGB-D odometry with OpenCV 5. W is the first camera frame.

    Construct with a :class:`RgbdOdometryConfig` or its fields as keyword arguments, e.g.
    ``RgbdOdometry(max_depth_m=6.0, downscale=2)``. Frames need ``depth`` (float32 metres,
    0 = invalid), ``intrinsics`` and, except for ``odometry_type='depth'``, ``rgb``.

    Attributes:
        num_failures: frames whose pose was extrapolated because registration failed.
        num_fallbacks: frames registered to the previous frame after the keyframe failed.
    """

    def __init__(self, config: RgbdOdometryConfig | None = None, **options) -> None:
        if config is not None and options:
            raise TypeError("pass either a RgbdOdometryConfig or keyword options, not both")
        self.config = config if config is not None else RgbdOdometryConfig(**options)
        c = self.config
        if len(c.min_gradient_magnitudes) != len(c.iter_counts):
            raise ValueError(
                "RgbdOdometryConfig: min_gradient_magnitudes needs one value per iter_counts level"
            )
        if c.max_depth_m <= c.min_depth_m:
            raise ValueError("RgbdOdometryConfig: max_depth_m must exceed min_depth_m")
        self._odometry = None
        self._downscale = 1
        self._shape: tuple[int, int] | None = None
        self._keyframe = None
        self._T_W_key = np.eye(4)
        self._previous = None
        self._T_W_prev = np.eye(4)
        self._T_prev_prev2 = np.eye(4)  # last relative motion, for the constant-velocity guess
        self.num_failures = 0
        self.num_fallbacks = 0
        self._key_cloud = None  # (points, normals, tree) of the keyframe for the covariance
        self._prev_cloud = None
        self._cov_chain = np.zeros((6, 6))  # since restart_covariance(), at the current keyframe
        self._cov_key_cur = np.zeros((6, 6))
        self._cov_complete = True  # every registration since restart_covariance() had its Hessian

    def _build(self, frame: Frame) -> None:
        import cv2

        c = self.config
        intr = frame.intrinsics
        s = self._downscale = self._choose_downscale(frame)
        K = np.array(
            [
                [intr.fx / s, 0.0, (intr.cx + 0.5) / s - 0.5],
                [0.0, intr.fy / s, (intr.cy + 0.5) / s - 0.5],
                [0.0, 0.0, 1.0],
            ],
            dtype=np.float32,
        )
        settings = cv2.OdometrySettings()
        settings.setCameraMatrix(K)
        settings.setMinDepth(c.min_depth_m)
        settings.setMaxDepth(c.max_depth_m)
        settings.setMaxDepthDiff(c.max_depth_diff_m)
        settings.setMaxPointsPart(c.max_points_part)
        settings.setIterCounts(_level_values(c.iter_counts, np.int32))
        settings.setMinGradientMagnitudes(_level_values(c.min_gradient_magnitudes, np.float32))
        settings.setMaxTranslation(c.max_translation_m)
        settings.setMaxRotation(c.max_rotation_deg)
        otype = {
            "rgbd": cv2.OdometryType_RGB_DEPTH,
            "depth": cv2.OdometryType_DEPTH,
            "rgb": cv2.OdometryType_RGB,
        }[c.odometry_type]
        algtype = {"common": cv2.OdometryAlgoType_COMMON, "fast": cv2.OdometryAlgoType_FAST}[
            c.algorithm
        ]
        self._odometry = cv2.Odometry(otype, settings, algtype)
        self._shape = frame.depth.shape

    def _choose_downscale(self, frame: Frame) -> int:
        if self.config.downscale is not None:
            return self.config.downscale
        return max(1, round(frame.depth.shape[1] / 320))

    @property
    def downscale(self) -> int | None:
        """Downscale factor in use (None before the first frame when chosen automatically)."""
        return self._downscale if self._odometry is not None else self.config.downscale

    def _check(self, frame: Frame) -> None:
        if frame.depth is None or frame.intrinsics is None:
            raise DatasetError(
                f"frame {frame.index}: RGB-D odometry needs a depth image and intrinsics; "
                "use an RGB-D source"
            )
        if self.config.odometry_type != "depth" and frame.rgb is None:
            raise DatasetError(
                f"frame {frame.index}: RGB-D odometry needs a colour image; use an RGB-D source "
                "or odometry_type='depth'"
            )
        if frame.rgb is not None and frame.rgb.shape[:2] != frame.depth.shape:
            raise DatasetError(
                f"frame {frame.index}: colour image is {frame.rgb.shape[:2]} but depth is "
                f"{frame.depth.shape}; register colour to depth in the source"
            )
        if self._shape is not None and frame.depth.shape != self._shape:
            raise DatasetError(
                f"frame {frame.index}: depth is {frame.depth.shape}, earlier frames were "
                f"{self._shape}; all frames of a sequence must have the same size"
            )
        if not np.any(frame.depth > 0):
            raise DatasetError(f"frame {frame.index}: depth image has no valid pixel")

    def _prepare(self, frame: Frame):
        """The frame prepared for ``cv2.Odometry``."""
        import cv2

        depth = np.asarray(frame.depth, dtype=np.float32)
        depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
        gray = None
        if frame.rgb is not None:
            gray = cv2.cvtColor(np.ascontiguousarray(frame.rgb), cv2.COLOR_RGB2GRAY)
        s = self._downscale
        if s > 1:
            depth = _downscale_depth(depth, s, self.config.max_depth_diff_m)
            if gray is not None:
                h, w = depth.shape
                gray = cv2.resize(gray[: h * s, : w * s], (w, h), interpolation=cv2.INTER_AREA)
        odometry_frame = (
            cv2.OdometryFrame(depth=depth)
            if gray is None
            else cv2.OdometryFrame(depth=depth, image=gray)
        )
        self._odometry.prepareFrame(odometry_frame)
        return odometry_frame

    def _relative(self, reference, current) -> np.ndarray | None:
        """``T_ref_cur`` or None when OpenCV reports failure."""
        ok, Rt = self._odometry.compute(reference, current)
        if not ok or Rt is None or not np.all(np.isfinite(Rt)):
            return None
        return np.linalg.inv(np.asarray(Rt, dtype=np.float64))

    def register(self, frame: Frame) -> OdometryResult:
        self._check(frame)
        if self._odometry is None:
            self._build(frame)
        current = self._prepare(frame)
        if self._keyframe is None:
            self._keyframe = self._previous = current
            self._T_W_key = self._T_W_prev = np.eye(4)
            self._key_cloud = self._prev_cloud = self._cloud(frame)
            self._cov_key_prev = np.zeros((6, 6))
            return OdometryResult(np.eye(4), covariance=self._covariance_since_restart())

        new_keyframe = False
        cloud = self._cloud(frame)
        T_key_cur = self._relative(self._keyframe, current)
        if T_key_cur is not None:
            T_W_cur = self._T_W_key @ T_key_cur
            cov_key_cur = self._registration_covariance(self._key_cloud, cloud, T_key_cur)
        else:
            T_prev_cur = None
            if self._previous is not self._keyframe:
                T_prev_cur = self._relative(self._previous, current)
            if T_prev_cur is not None:
                self.num_fallbacks += 1
                cov_prev_cur = self._registration_covariance(self._prev_cloud, cloud, T_prev_cur)
            else:
                self.num_failures += 1
                logger.warning(
                    "frame %d: RGB-D odometry failed; assuming constant velocity (%d failures)",
                    frame.index,
                    self.num_failures,
                )
                T_prev_cur = self._T_prev_prev2
                cov_prev_cur = np.diag([0.05**2] * 3 + [0.1**2] * 3)
            T_W_cur = self._T_W_prev @ T_prev_cur
            # Chained through the previous frame: keyframe -> previous -> current.
            Ad = adjoint(np.linalg.inv(T_prev_cur))
            cov_key_cur = Ad @ self._cov_key_prev @ Ad.T + cov_prev_cur
            new_keyframe = True

        T_key_cur = np.linalg.inv(self._T_W_key) @ T_W_cur
        c = self.config
        if (
            new_keyframe
            or np.linalg.norm(T_key_cur[:3, 3]) >= c.keyframe_translation_m
            or _rotation_deg(T_key_cur) >= c.keyframe_rotation_deg
        ):
            Ad = adjoint(np.linalg.inv(T_key_cur))
            self._cov_chain = Ad @ self._cov_chain @ Ad.T + cov_key_cur
            cov_key_cur = np.zeros((6, 6))
            self._keyframe, self._T_W_key = current, T_W_cur
            self._key_cloud = cloud
        self._cov_key_cur = self._cov_key_prev = cov_key_cur
        self._prev_cloud = cloud
        self._T_prev_prev2 = np.linalg.inv(self._T_W_prev) @ T_W_cur
        self._previous, self._T_W_prev = current, T_W_cur
        return OdometryResult(T_W_cur.copy(), covariance=self._covariance_since_restart())

    def _cloud(self, frame: Frame):
        """A thinned copy of the frame's points and normals with a k-d tree (or None)."""
        n = self.config.covariance_points
        if n == 0 or frame.normals is None or len(frame.points) < 50:
            return None
        from scipy.spatial import cKDTree

        step = max(1, len(frame.points) // n)
        points = np.asarray(frame.points[::step], dtype=np.float64)
        normals = np.asarray(frame.normals[::step], dtype=np.float64)
        good = np.linalg.norm(normals, axis=1) > 0.5
        points, normals = points[good], normals[good]
        return points, normals, cKDTree(points)

    def _registration_covariance(self, reference, current, T_ref_cur: np.ndarray) -> np.ndarray:
        """``factor * sigma^2 H^-1`` of the point-to-plane cost at the estimate, or zeros."""
        if reference is None or current is None:
            self._cov_complete = False
            return np.zeros((6, 6))
        result = point_to_plane_hessian(
            reference[0],
            reference[1],
            current[0],
            T_ref_cur,
            max_distance_m=self.config.covariance_max_distance_m,
            tree=reference[2],
        )
        if result.num_inliers < 50:
            return np.diag([0.05**2] * 3 + [0.1**2] * 3)
        return result.covariance(self.config.covariance_factor)

    def _covariance_since_restart(self) -> np.ndarray | None:
        """Covariance (``[rot, trans]``, right perturbation) of the motion from the frame of the
        latest :meth:`restart_covariance` to the latest frame. None when the covariance is off
        or a frame had no normals to evaluate it."""
        if self.config.covariance_points == 0 or not self._cov_complete:
            return None
        T_key_cur = np.linalg.inv(self._T_W_key) @ self._T_W_prev
        Ad = adjoint(np.linalg.inv(T_key_cur))
        covariance = Ad @ self._cov_chain @ Ad.T + self._cov_key_cur
        return 0.5 * (covariance + covariance.T)

    def restart_covariance(self) -> None:
        self._cov_complete = True
        if self.config.covariance_points == 0 or self._keyframe is None:
            return
        # The latest frame becomes the origin. The next motion starts with the way back from it
        # to its keyframe: the covariance of inv(T_key_cur) is Ad(T_key_cur) cov Ad(T_key_cur)^T.
        Ad_back = adjoint(np.linalg.inv(self._T_W_key) @ self._T_W_prev)
        self._cov_chain = Ad_back @ self._cov_key_cur @ Ad_back.T
