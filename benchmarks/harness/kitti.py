"""The generated KITTI-00 LiDAR sequence every LiDAR benchmark uses: a 64-beam LiDAR simulated
along the real KITTI 00 trajectory (generated on first use, then cached), in two windows shared
by all benchmarks: :data:`FULL` and :data:`QUICK` (which still revisits the start from frame 1559
on). A benchmark takes the first N frames of a window.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks.harness.paths import DATA

KITTI_POSES = DATA / "kitti" / "poses" / "00.txt"
KITTI_CALIB = DATA / "kitti" / "sequences" / "00" / "calib.txt"


@dataclass(frozen=True)
class Window:
    """Which poses of KITTI 00 are scanned, and how finely."""

    num_frames: int
    step: int
    azimuth_steps: int

    def describe(self, frames: int | None = None) -> str:
        n = self.num_frames if frames is None else min(frames, self.num_frames)
        every = "every" if self.step == 1 else f"every {self.step}."
        return (
            f"KITTI 00 poses 0-{(n - 1) * self.step}, {every} pose ({n} scans, "
            f"{self.azimuth_steps} firings per revolution)"
        )


FULL = Window(num_frames=4541, step=1, azimuth_steps=2048)
QUICK = Window(num_frames=550, step=3, azimuth_steps=1024)


STREETS: dict[str, dict[str, Any]] = {
    "standard, seed 0": {},
    "standard, seed 1": {"seed": 1},
    "standard, seed 2": {"seed": 2},
    "sparse": {"street_style": "sparse"},
    "periodic": {"street_style": "periodic"},
    "1024 firings": {"azimuth_steps": 1024},
    "2048 firings": {"azimuth_steps": 2048},
    "noise 5 cm + 2 % dropout": {"range_noise_m": 0.05, "dropout": 0.02},
    "KITTI angle correction, ideal scans": {"loader_options": {"correct_vertical_angle": True}},
}
"""The data variants of the generated street: generator keyword arguments on top of the
window's (:func:`kitti_source`)."""
STANDARD_STREET = "standard, seed 0"


def window(quick: bool) -> Window:
    """The quick or the full window."""
    return QUICK if quick else FULL


def have_kitti() -> bool:
    """Whether the KITTI 00 poses and calibration the generator needs are present."""
    return KITTI_POSES.is_file() and KITTI_CALIB.is_file()


def kitti_source(
    quick: bool, num_frames: int | None = None, relief_m: float = 0.0, first: int = 0, **variant
):
    """Frames ``first`` to ``num_frames - 1`` of the quick or full window (all by default), with
    hills of ``relief_m`` beside the road (another cached sequence when non-zero); ``variant``
    overrides generator settings (seed, street_style, azimuth_steps, range_noise_m, dropout)."""
    from frontends.sources import make_source

    w = window(quick)
    settings = {
        "num_frames": w.num_frames,
        "step": w.step,
        "azimuth_steps": w.azimuth_steps,
        "terrain_relief_m": relief_m,
        **variant,
    }
    return make_source(
        "generated",
        kind="lidar",
        trajectory="kitti",
        kitti_poses=KITTI_POSES,
        kitti_calib=KITTI_CALIB,
        start=0,
        frames=slice(first, num_frames),
        **settings,
    )


def kitti_root(source) -> Path:
    """The KITTI-layout root (``sequences/00`` below it) of a generated source."""
    return Path(source.sequence_dir).parents[1]
