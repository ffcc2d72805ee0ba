"""KISS-ICP's KITTI vertical-angle correction, chosen from the road in the scans
(frontends/sources/beam_correction.py): off for ideal generated scans, on for the same scans
lowered by the HDL-64E's 0.205 deg, an explicit choice kept with one warning where the road
disagrees, and real HDL-64E scans not refused the correction."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from frontends.sources import make_source
from frontends.sources.beam_correction import (
    VERTICAL_ANGLE_OFFSET_DEG,
    choose_correction,
    correct_vertical_angle,
    examined_indices,
)
from frontends.sources.kitti import KittiSource, read_kitti_bin
from frontends.sources.pcd_folder import read_pcd_points
from slam.assembly.source_config import KittiOptions
from tests.pipeline_setups import STREET

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REAL_KITTI = DATA / "kitti" / "real_scans"
KITTI_RAW = DATA / "kitti_raw_22"


@pytest.fixture(scope="module")
def street_root() -> Path:
    """The KITTI-layout root of the generated street (ideal beam elevations)."""
    return make_source("generated", **STREET).cache_dir


def _examined_scans(root: Path) -> list[np.ndarray]:
    source = KittiSource(root, "00", correct_vertical_angle=False)
    return [source._read(int(i))[:, :3].astype(np.float64) for i in examined_indices(len(source))]


def test_the_numpy_correction_is_kiss_icps():
    """The source corrects scans in numpy: KISS-ICP's C++ values to a rounding (bit for bit on
    x86_64 builds), points on the z axis and float32 scans included."""
    from kiss_icp.pybind import kiss_icp_pybind

    points = np.random.default_rng(0).normal(0.0, 20.0, (20_000, 3)).astype(np.float32)
    points[:3] = [[0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [0.0, 0.0, -1.5]]
    theirs = kiss_icp_pybind._correct_kitti_scan(
        kiss_icp_pybind._Vector3dVector(points.astype(np.float64))
    )
    ours = correct_vertical_angle(points)
    assert ours.dtype == np.float64 and ours.flags.c_contiguous
    np.testing.assert_allclose(ours, np.asarray(theirs), rtol=0.0, atol=1e-12)
    lowered = correct_vertical_angle(points[3:], -VERTICAL_ANGLE_OFFSET_DEG)
    np.testing.assert_allclose(correct_vertical_angle(lowered), points[3:], atol=1e-9)


def test_auto_leaves_ideal_generated_scans_uncorrected(street_root, caplog):
    with caplog.at_level(logging.INFO, logger="frontends.sources.beam_correction"):
        source = KittiSource(street_root, "00", correct_vertical_angle="auto")
    choice = source.correction
    assert (choice.apply, choice.needed) == (False, False)
    assert abs(choice.cone_angle_deg) < 0.05
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    record = source.data_choices()["kitti_vertical_angle_correction"]
    assert record["setting"] == "auto" and record["applied"] is False


def test_an_explicit_correction_of_ideal_scans_is_kept_with_one_warning(street_root, caplog):
    with caplog.at_level(logging.WARNING, logger="frontends.sources.beam_correction"):
        source = KittiSource(street_root, "00", correct_vertical_angle=True)
    assert source.correct_vertical_angle is True
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "\n" not in warnings[0]
    assert "correct_vertical_angle=true looks wrong" in warnings[0]
    assert "set it to auto or false" in warnings[0]


def test_scans_with_the_hdl64e_error_get_the_correction(street_root, caplog):
    lowered = [
        correct_vertical_angle(scan, -VERTICAL_ANGLE_OFFSET_DEG)
        for scan in _examined_scans(street_root)
    ]
    choice = choose_correction("auto", lowered.__getitem__, len(lowered), "lowered street")
    assert (choice.apply, choice.needed) == (True, True)
    assert abs(choice.cone_angle_deg + VERTICAL_ANGLE_OFFSET_DEG) < 0.05
    with caplog.at_level(logging.WARNING, logger="frontends.sources.beam_correction"):
        kept = choose_correction(False, lowered.__getitem__, len(lowered), "lowered street")
    assert kept.apply is False
    assert "set it to auto or true" in caplog.text


def _lane(cone_angle_deg: float, seed: int) -> np.ndarray:
    """The road ahead of and behind a sensor 1.73 m above it, bent into a cone of this angle."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(4.5, 11.5, 1500) * rng.choice([-1.0, 1.0], 1500)
    z = -1.73 + np.tan(np.radians(cone_angle_deg)) * np.abs(x)
    return np.column_stack([x, rng.uniform(-2.4, 2.4, 1500), z])


@pytest.mark.parametrize("offset_deg, needed", [(0.0, False), (-VERTICAL_ANGLE_OFFSET_DEG, True)])
def test_a_drive_whose_first_scans_do_not_tell_is_examined_further(offset_deg, needed, caplog):
    """Roads that bend differently from place to place (one scan's cone angle spread by
    0.45 deg): the first 40 scans of a 2,000-scan drive leave it undecided, and alone would be
    corrected, with a warning where their median leans to 0; the 200 examined after them
    decide, without a warning."""
    angles = np.random.default_rng(3).normal(offset_deg, 0.45, 2000)
    first = examined_indices(len(angles))
    with caplog.at_level(logging.INFO, logger="frontends.sources.beam_correction"):
        undecided = choose_correction(
            "auto", lambda i: _lane(angles[first[i]], i), len(first), "first scans"
        )
    assert (undecided.apply, undecided.needed) == (True, None)
    assert len(undecided.per_scan_deg) == len(first)
    warned = caplog.records[-1].levelno == logging.WARNING
    assert warned == (not needed)
    assert ("leans to scans without the error" in caplog.records[-1].getMessage()) == warned
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="frontends.sources.beam_correction"):
        choice = choose_correction("auto", lambda i: _lane(angles[i], i), len(angles), "drive")
    assert (choice.apply, choice.needed) == (needed, needed)
    assert len(first) < len(choice.per_scan_deg) <= len(first) + 200
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


@pytest.mark.skipif(not REAL_KITTI.is_dir(), reason=f"real KITTI scans not found at {REAL_KITTI}")
def test_real_hdl64e_odometry_scans_are_not_refused_the_correction():
    scans = [
        read_kitti_bin(path)[:, :3].astype(np.float64) for path in sorted(REAL_KITTI.rglob("*.bin"))
    ]
    choice = choose_correction("auto", scans.__getitem__, len(scans), str(REAL_KITTI))
    assert choice.apply is True and choice.needed is not False


@pytest.mark.skipif(not KITTI_RAW.is_dir(), reason=f"KITTI raw scans not found at {KITTI_RAW}")
def test_real_hdl64e_raw_scans_need_the_correction():
    scans = [read_pcd_points(path) for path in sorted(KITTI_RAW.glob("*.pcd"))]
    choice = choose_correction("auto", scans.__getitem__, len(scans), str(KITTI_RAW))
    assert (choice.apply, choice.needed) == (True, True)


def test_the_setting_takes_auto_true_or_false_only():
    assert KittiOptions().correct_vertical_angle == "auto"
    assert KittiOptions(correct_vertical_angle=False).correct_vertical_angle is False
    with pytest.raises(ValidationError):
        KittiOptions(correct_vertical_angle="maybe")


def test_a_run_records_the_choice_in_its_metrics(lidar_run):
    metrics = json.loads((lidar_run.folder / "metrics.json").read_text())
    record = metrics["input"]["kitti_vertical_angle_correction"]
    assert record["applied"] is False and record["needed_by_the_road"] is False
    assert len(record["per_scan_road_cone_angle_deg"]) > 1
