"""Whether KITTI-layout scans need KISS-ICP's vertical-angle correction, judged from the scans.

KITTI's own HDL-64E reports its beams 0.205 deg lower than they fire, so level ground seen from
the sensor bends down into a cone: its height falls by ``tan(0.205 deg)`` per metre of horizontal
range. KISS-ICP's correction (``kiss_icp_pybind._correct_kitti_scan``) raises every point by
0.205 deg, which flattens that cone; on KITTI-layout scans without the error (another LiDAR, a
simulation) it bends level ground up into a cone instead, and KISS-ICP's pitch drifts.

The evidence is the road ahead of and behind the sensor (the lane it drives in, away from kerbs
and sidewalks), fitted by ``z = a + b x + c y + k |x|``: the cone angle ``atan(k)`` is about
-0.205 deg where the correction is needed and about 0 where it is not. The road's own shape (a
sag, a crest, a turn) bends one place's fit by more, so the decision takes the median over scans
spread over the whole selection, and decides nothing where that median is near neither value or
not a standard error nearer one of them. Where a first set of scans does not tell, more are
examined: a long drive's roads vary more than a short one's.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

log = logging.getLogger(__name__)

VERTICAL_ANGLE_OFFSET_DEG = 0.205
"""KISS-ICP's correction of the KITTI HDL-64E's beam elevations."""
CorrectionSetting = bool | Literal["auto"]

SCANS_EXAMINED = 40
"""Scans whose road is fitted, spread evenly over the selected frames (the first among them):
one scan's cone angle spreads over an interquartile range of about 0.5 deg on the generated
KITTI 00 street, so it takes tens of them to tell 0 from -0.205."""
MORE_SCANS_EXAMINED = 200
"""Where the first :data:`SCANS_EXAMINED` do not tell, the road of this many scans spread evenly
over the selection is fitted too (those already fitted are kept). On the 4,541 scans of the
generated KITTI 00 street (2048 firings, no beam error), the first 40 put the median at
-0.001 +- 0.053 deg, 1.9 standard errors from the middle (-0.1025), short of the 2 that turn the
correction off; all 238 put it at +0.033 +- 0.024, 5.6 away."""
MIN_SCANS_TO_TURN_OFF = 30
"""Fewer scans with road than this never turn the correction off. Over windows of the generated
street's 550-scan quick window, scans lowered by 0.205 deg were judged 'not needed' in 3 of 103
windows of 40 scans, 1 of 71 of 60 and none of 150 or more; ideal scans were judged 'needed' in
1 of 103 of 40 and none beyond (the rest: not told, so corrected)."""
_LANE_HALF_WIDTH_M = 2.5
_LANE_RANGE_M = (4.0, 12.0)
"""The road fitted: within this half-width of the sensor's x axis, at these distances ahead and
behind (past the car, short of where a sag or crest bends the road more than the cone does)."""
_GATES_M = (0.4, 0.2, 0.1, 0.05)
"""Residual gates of the successive road fits (the last one keeps the road, not the cars)."""
_MIN_ROAD_POINTS = 300
"""Fewer road points than this in a scan: the scan gives no evidence."""


def correct_vertical_angle(
    points: np.ndarray, offset_deg: float = VERTICAL_ANGLE_OFFSET_DEG
) -> np.ndarray:
    """KISS-ICP's KITTI correction in numpy: every point raised by ``offset_deg`` of elevation
    (rotated about ``p x z``; a negative offset lowers it); points on the z axis are scaled by
    the cosine as KISS-ICP does. ``points`` (N, 3) of any float type; returns (N, 3) float64.

    At the default offset the values equal ``kiss_icp_pybind._correct_kitti_scan``'s bit for
    bit: the rotation matrix is Eigen's ``AngleAxisd::toRotationMatrix`` and each row's sum is
    taken in the order of its 3x3 product (the first two rows as one SIMD packet, the third
    unrolled), at a quarter of the CPU (1.5 ms against 6.2 ms a 127k-point scan, converting
    included).
    """
    x, y, z = (np.asarray(points[:, k], dtype=np.float64) for k in range(3))
    angle = (offset_deg * math.pi) / 180.0
    sin, cos = math.sin(angle), math.cos(angle)
    # the unit axis (ax, ay, 0) = normalised p x z, left as it is where that is zero (Eigen)
    norm = y * y
    norm += x * x
    np.sqrt(norm, out=norm)
    norm[norm == 0.0] = 1.0
    ax = y / norm
    ay = np.negative(x)
    ay /= norm
    r01 = ax * (1.0 - cos)
    r01 *= ay  # the matrix entries (0, 1) and (1, 0)
    corrected = np.empty((len(x), 3))
    row, term = np.empty_like(x), norm  # reused buffers
    # rows 0 and 1: ((c1 a a + cos) p + r01 q) + (s b) z, with (a, p, q, b, s) =
    # (ax, x, y, ay, sin) and (ay, y, x, ax, -sin)
    for k, (a, p, q, b, s) in enumerate(((ax, x, y, ay, sin), (ay, y, x, ax, -sin))):
        np.multiply(a, 1.0 - cos, out=row)
        row *= a
        row += cos
        row *= p
        np.multiply(r01, q, out=term)
        row += term
        np.multiply(b, s, out=term)
        term *= z
        row += term
        corrected[:, k] = row
    np.multiply(ax, sin, out=row)  # row 2: -(sin ay) x + ((sin ax) y + cos z)
    row *= y
    np.multiply(z, cos, out=term)
    row += term
    np.multiply(ay, -sin, out=term)
    term *= x
    row += term
    corrected[:, 2] = row
    return corrected


def road_cone_angle_deg(points: np.ndarray) -> float | None:
    """The cone angle of the road ahead of and behind the sensor in one scan (sensor frame, x
    forward, z up): ``atan(k)`` of ``z = a + b x + c y + k |x|`` fitted to it, in degrees, or
    None where the scan shows too little road. The road starts as the densest height band
    below the sensor and is refined by fits with shrinking residual gates."""
    x, y, z = np.asarray(points, dtype=np.float64).T
    lane = (np.abs(y) < _LANE_HALF_WIDTH_M) & (z < 0.0)
    lane &= (np.abs(x) > _LANE_RANGE_M[0]) & (np.abs(x) < _LANE_RANGE_M[1])
    x, y, z = x[lane], y[lane], z[lane]
    if len(z) < _MIN_ROAD_POINTS:
        return None
    counts, edges = np.histogram(z, bins=np.arange(z.min(), 0.1, 0.1))
    densest = int(np.argmax(counts))
    design = np.column_stack([np.ones_like(x), x, y, np.abs(x)])
    coefficients = np.array([0.5 * (edges[densest] + edges[densest + 1]), 0.0, 0.0, 0.0])
    for gate in _GATES_M:
        road = np.abs(design @ coefficients - z) < gate
        if int(road.sum()) < _MIN_ROAD_POINTS:
            return None
        coefficients = np.linalg.lstsq(design[road], z[road], rcond=None)[0]
    return float(np.degrees(np.arctan(coefficients[3])))


def examined_indices(num_frames: int, count: int = SCANS_EXAMINED) -> np.ndarray:
    """Positions (into the selected frames) of ``count`` scans spread evenly over them, the
    first included (all of them when there are fewer)."""
    return np.unique(np.linspace(0, num_frames - 1, min(count, num_frames)).astype(int))


@dataclass(frozen=True)
class CorrectionChoice:
    """What a KITTI source does about the vertical-angle correction, and why.

    Attributes:
        setting: the configured value (``"auto"``, True or False).
        apply: whether the scans are corrected.
        needed: what the road says (None: it does not tell, see :func:`choose_correction`).
        cone_angle_deg: median over the examined scans of the road's cone angle without the
            correction: about -0.205 for KITTI's HDL-64E, about 0 without the error.
        cone_angle_error_deg: the median's standard error (:func:`median_and_error`).
        per_scan_deg: each examined scan's cone angle (None where it showed too little road).
    """

    setting: CorrectionSetting
    apply: bool
    needed: bool | None
    cone_angle_deg: float | None
    cone_angle_error_deg: float | None
    per_scan_deg: list[float | None] = field(default_factory=list)

    def record(self) -> dict[str, Any]:
        """The choice and its evidence, for a run's ``metrics.json``."""
        return {
            "setting": self.setting,
            "applied": self.apply,
            "needed_by_the_road": self.needed,
            "road_cone_angle_deg": self.cone_angle_deg,
            "road_cone_angle_standard_error_deg": self.cone_angle_error_deg,
            "road_cone_angle_if_needed_deg": -VERTICAL_ANGLE_OFFSET_DEG,
            "per_scan_road_cone_angle_deg": self.per_scan_deg,
        }


def median_and_error(angles: Sequence[float]) -> tuple[float, float]:
    """The median of per-scan cone angles and its standard error (from their interquartile
    range: ``1.253 sigma / sqrt(n)``, ``sigma = IQR / 1.349``)."""
    values = np.asarray(angles, dtype=np.float64)
    q25, q50, q75 = np.percentile(values, [25, 50, 75])
    return float(q50), float(1.253 * (q75 - q25) / 1.349 / np.sqrt(len(values)))


def needed_by(cone_angle_deg: float | None, standard_error_deg: float, scans: int) -> bool | None:
    """What the road's median cone angle says: needed where it lies within half the offset of
    -0.205 deg and a standard error nearer it than 0; not needed, which departs from what
    KISS-ICP does for KITTI, only on :data:`MIN_SCANS_TO_TURN_OFF` scans or more with the median
    within half the offset of 0 and two standard errors nearer it; None elsewhere (the road is
    no plane either way, or too few scans agree)."""
    if cone_angle_deg is None:
        return None
    half = 0.5 * VERTICAL_ANGLE_OFFSET_DEG
    if -3.0 * half < cone_angle_deg < -half - standard_error_deg:
        return True
    if scans >= MIN_SCANS_TO_TURN_OFF and -half + 2.0 * standard_error_deg < cone_angle_deg < half:
        return False
    return None


def _road_says(
    angles: Sequence[float | None],
) -> tuple[bool | None, float | None, float | None, int]:
    """What per-scan cone angles (None: no road) say: :func:`needed_by`, their median and its
    standard error (both None without a measured scan), and how many scans had road."""
    measured = [a for a in angles if a is not None]
    if not measured:
        return None, None, None, 0
    median, error = median_and_error(measured)
    return needed_by(median, error, len(measured)), median, error, len(measured)


def choose_correction(
    setting: CorrectionSetting,
    scan_at: Callable[[int], np.ndarray | None],
    num_scans: int,
    where: str,
) -> CorrectionChoice:
    """Decide from raw scans whether to correct them: ``scan_at(i)`` gives the points (N, 3) of
    the i-th of ``num_scans`` in the sensor frame (None where it cannot be read);
    :data:`SCANS_EXAMINED` of them, spread evenly, are examined, and :data:`MORE_SCANS_EXAMINED`
    where those do not tell. ``"auto"`` follows the road, and where it does not tell, corrects
    (what KISS-ICP does for KITTI), with a warning when the median of enough scans lies nearer 0
    than -0.205 (the correction then looks more likely wrong than right); an explicit True or
    False is kept, with one warning when the road says otherwise. ``where`` names the scans in
    the log."""
    angles: dict[int, float | None] = {}
    for count in (SCANS_EXAMINED, MORE_SCANS_EXAMINED):
        for i in examined_indices(num_scans, count).tolist():
            if i not in angles:
                scan = scan_at(i)
                angles[i] = None if scan is None else road_cone_angle_deg(scan)
        needed, median, error, measured = _road_says(list(angles.values()))
        if needed is not None:
            break
    per_scan = [angles[i] for i in sorted(angles)]
    apply = (needed is not False) if setting == "auto" else bool(setting)
    evidence = (
        "too little road in the scans to tell"
        if median is None
        else f"the road's median cone angle over {measured} scans is {median:+.3f} "
        f"+- {error:.3f} deg (-{VERTICAL_ANGLE_OFFSET_DEG} where the correction is needed, 0 "
        "where not" + ("; neither, so it does not tell)" if needed is None else ")")
    )
    leans_off = median is not None and median > -0.5 * VERTICAL_ANGLE_OFFSET_DEG
    if setting == "auto" and needed is None and leans_off and measured >= MIN_SCANS_TO_TURN_OFF:
        log.warning(
            "%s: KITTI vertical-angle correction on, as KISS-ICP does for KITTI, though the "
            "road leans to scans without the error: %s; if they are not from KITTI's HDL-64E, "
            "set source.kitti.correct_vertical_angle=false",
            where,
            evidence,
        )
    elif setting == "auto":
        log.info(
            "%s: KITTI vertical-angle correction %s: %s", where, "on" if apply else "off", evidence
        )
    elif needed is not None and needed != apply:
        log.warning(
            "%s: source.kitti.correct_vertical_angle=%s looks wrong for these scans: %s; "
            "set it to auto or %s",
            where,
            str(apply).lower(),
            evidence,
            str(needed).lower(),
        )
    return CorrectionChoice(setting, apply, needed, median, error, per_scan)
