"""Odometry speed and drift: KISS-ICP (LiDAR) and OpenCV RGB-D odometry.

    python -m benchmarks.bench_odometry [--quick]

Writes ``benchmarks/results/odometry.md``: KISS-ICP on generated 64-beam scans along KITTI 00
(frames 0-499, ``--quick`` 0-149; the generated loop without ``../shared/data``) and its speed on
five real HDL-64E scans; RGB-D odometry on a generated room lap and on real 7-Scenes redkitchen
frames (with, in full mode, the variants that motivated the defaults). Frames/s count the
``register`` calls only; drift is ATE (SE(3)-aligned), RPE between consecutive frames, end-point
error as % of the path length, and the KITTI relative error where the path is long enough.
"""

from __future__ import annotations

import logging
import sys
import time

import numpy as np

from benchmarks.harness.cli import bench_parser
from benchmarks.harness.kitti import KITTI_POSES, have_kitti, kitti_source, window
from benchmarks.harness.machine import section_header
from benchmarks.harness.paths import DATA, RESULTS_DIR
from benchmarks.harness.repeat import REPEATS, Timing, repeats_line
from benchmarks.harness.results import table
from common.atomic_io import write_text_atomic
from frontends.odometry import make_odometry
from frontends.sources import make_source
from slam.evaluation.metrics import (
    KITTI_LENGTHS_M,
    ate_rmse,
    kitti_relative_error,
    rpe,
    trajectory_length_m,
)

log = logging.getLogger("benchmarks.bench_odometry")

RESULTS = RESULTS_DIR / "odometry.md"


def _run(name: str, method: str, options: dict, source, *, kitti_lengths=None) -> list[str]:
    """Register every frame of ``source`` and score it against its ground truth: a table row
    (:data:`HEADER`)."""
    rates = []
    for _ in range(REPEATS):  # a fresh odometry each time; the poses are the same every run
        odometry = make_odometry(method, **options)
        poses = []
        seconds = 0.0
        for frame in source:
            t0 = time.perf_counter()
            poses.append(odometry.register(frame).T_W_S)
            seconds += time.perf_counter() - t0
        rates.append(len(poses) / seconds)
    est = np.stack(poses)
    gt = np.linalg.inv(source.gt_poses[0]) @ source.gt_poses
    length = trajectory_length_m(gt)
    relative = rpe(est, gt, 1)
    kitti = "-"
    if kitti_lengths:
        t_err, r_err = kitti_relative_error(est, gt, lengths_m=kitti_lengths)
        lengths = ",".join(f"{x:g}" for x in kitti_lengths)
        kitti = f"{t_err:.2f} % / {r_err:.2f} deg/100m ({lengths} m)"
    from frontends.odometry.rgbd import RgbdOdometry

    failures = "-"
    if isinstance(odometry, RgbdOdometry):  # the only one with a keyframe fallback
        failures = f"{odometry.num_failures} / {odometry.num_fallbacks}"
    end_drift = 100 * np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]) / length
    row = [
        name,
        ", ".join(f"{k}={v}" for k, v in options.items()) or "defaults",
        len(est),
        f"{length:.1f}",
        f"{Timing(rates):.1f}",
        f"{ate_rmse(est, gt):.4f}",
        f"{relative.trans_rmse_m:.4f} / {relative.rot_rmse_deg:.3f}",
        f"{end_drift:.2f}",
        kitti,
        failures,
    ]
    log.info("%s %s: %s", name, method, row)
    return row


def _kitti_lengths(length_m: float) -> tuple[float, ...]:
    """KITTI's 100..800 m segments that fit in paths of 200 m or more, else shorter ones."""
    if length_m >= 200.0:
        return tuple(x for x in KITTI_LENGTHS_M if x < length_m)
    step = max(5.0, round(length_m / 8 / 5) * 5)
    return (step, 2 * step, 3 * step)


def lidar_rows(quick: bool) -> tuple[list[list], str]:
    num_frames = 150 if quick else 500
    t0 = time.perf_counter()
    if have_kitti():
        source_args = {"quick": quick, "num_frames": num_frames}
        what = "generated HDL-64E-like scans along " + window(quick).describe(num_frames)
        make = kitti_source
    else:
        log.warning("%s absent: using the generated loop trajectory", KITTI_POSES)
        num_frames = max(num_frames, 186)
        source_args = {"name": "generated", "kind": "lidar", "num_frames": num_frames}
        what = f"generated HDL-64E-like scans on the generated {num_frames}-frame loop"
        make = make_source
    source = make(**source_args)
    generation_s = time.perf_counter() - t0
    points = len(source[0].points)
    lengths = _kitti_lengths(trajectory_length_m(source.gt_poses))
    rows = [_run("LiDAR, " + what, "kiss-icp", {}, source, kitti_lengths=lengths)]
    if not quick and have_kitti():
        # The same scans from frame 20 on: separates the start (a straight street whose
        # geometry barely constrains motion along it while the constant-velocity model still
        # believes the car stands still) from steady-state drift.
        late = kitti_source(quick, num_frames, first=20)
        late_lengths = _kitti_lengths(trajectory_length_m(late.gt_poses))
        rows.append(
            _run(
                f"LiDAR, same scans from frame 20 to {num_frames - 1}",
                "kiss-icp",
                {},
                late,
                kitti_lengths=late_lengths,
            )
        )
    note = (
        f"{what}: {points} points in the first scan; generation or cache lookup took "
        f"{generation_s:.0f} s."
    )
    return rows, note


def real_scan_speed() -> str:
    scans = [DATA / "kitti" / "real_scans" / f"{i:06d}.bin" for i in range(10, 15)]
    if not all(p.is_file() for p in scans):
        return "Real KITTI scans absent: KISS-ICP speed on real scans not measured."
    from frontends.frame import Frame

    clouds = [np.fromfile(p, np.float32).reshape(-1, 4)[:, :3].astype(np.float64) for p in scans]
    odometry = make_odometry("kiss-icp")
    seconds = []
    steps = []
    previous = np.eye(4)
    for i, cloud in enumerate(clouds):
        t0 = time.perf_counter()
        T = odometry.register(Frame(i, 0.1 * i, cloud)).T_W_S
        seconds.append(time.perf_counter() - t0)
        steps.append(np.linalg.norm((np.linalg.inv(previous) @ T)[:3, 3]))
        previous = T
    mean_points = np.mean([len(c) for c in clouds])
    per_scan = Timing(seconds[1:]).scaled(1000)
    return (
        f"KISS-ICP on the 5 consecutive real HDL-64E scans ({mean_points:.0f} points each): "
        f"{per_scan:.0f} ms per scan after the first (median (min-max) of the "
        f"{len(seconds) - 1}; {1000 / per_scan:.1f} scans/s); estimated motion "
        f"{np.mean(steps[1:]):.2f} m per scan (no ground truth)."
    )


def room_rows(quick: bool) -> tuple[list[list], str]:
    width, height, num_frames = (320, 240, 150) if quick else (640, 480, 300)
    t0 = time.perf_counter()
    source = make_source(
        "generated", kind="rgbd", num_frames=num_frames, width=width, height=height
    )
    generation_s = time.perf_counter() - t0
    name = f"RGB-D, generated room lap {width}x{height}"
    rows = [_run(name, "rgbd", {}, source)]
    if not quick:
        rows.append(_run(name, "rgbd", {"downscale": 1}, source))
    note = (
        f"Generated room: one {trajectory_length_m(source.gt_poses):.1f} m lap in {num_frames} "
        f"frames; generation or cache lookup took {generation_s:.0f} s."
    )
    return rows, note


def seven_scenes_rows(quick: bool) -> tuple[list[list], str]:
    root = DATA / "7scenes_redkitchen"
    if not root.is_dir():
        return [], f"{root} absent: 7-Scenes not measured."
    num_frames = 100 if quick else 400
    source = make_source("7scenes", root=root, sequence="seq-01", frames=slice(0, num_frames))
    frames = list(source)  # load once: the variants below reuse the decoded images

    class Loaded:
        gt_poses = source.gt_poses

        def __iter__(self):
            return iter(frames)

    name = f"RGB-D, real 7-Scenes redkitchen seq-01 frames 0-{num_frames - 1} (640x480)"
    variants = [{}]
    if not quick:
        variants += [
            {"downscale": 1},
            {"keyframe_translation_m": 0.0},
            {"keyframe_translation_m": 0.1, "keyframe_rotation_deg": 5.0},
        ]
    rows = [_run(name, "rgbd", options, Loaded()) for options in variants]
    note = (
        "7-Scenes ground truth comes from KinectFusion, and colour is not registered to depth "
        "(a different camera), which hurts the photometric term."
    )
    return rows, note


HEADER = (
    "sequence | options | frames | path (m) | frames/s | ATE (m) | RPE (m / deg per frame) "
    "| end drift (% of path) | KITTI rel. error | failures / fallbacks"
)


def build_parser():
    return bench_parser(__doc__, "fewer frames, no variants")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("frontends.odometry.rgbd").setLevel(logging.ERROR)

    started = time.perf_counter()
    import cv2
    import torch

    threads = f"torch threads {torch.get_num_threads()}, OpenCV threads {cv2.getNumThreads()}"
    lidar, lidar_note = lidar_rows(args.quick)
    real_note = real_scan_speed()
    room, room_note = room_rows(args.quick)
    seven, seven_note = seven_scenes_rows(args.quick)
    elapsed = time.perf_counter() - started

    command = "python -m benchmarks.bench_odometry" + (" --quick" if args.quick else "")
    lines = [
        *section_header("Odometry", command),
        f"- {elapsed:.0f} s in all; {threads}",
        repeats_line(
            "Frames/s only: each sequence is registered that often by a fresh "
            "odometry; the poses, and so every error, are the same in every run."
        ),
        "- Frames/s: `register` calls only. ATE: RMSE after SE(3) Umeyama alignment without "
        "scale. End drift: end-point position error / ground-truth path length. KITTI relative "
        "error: devkit definition over the segment lengths given. Failures: frames "
        "extrapolated with constant velocity; fallbacks: frames registered to the previous "
        "frame after the keyframe failed (RGB-D only).",
        "",
        "### KISS-ICP (LiDAR)",
        "",
        *table(HEADER, lidar, "llrrrrlrll"),
        "",
        f"- {lidar_note}",
        "- The second row leaves out the first 20 scans, where KISS-ICP starts from a "
        "zero-velocity prediction; the difference between the rows is what that start costs.",
        f"- {real_note}",
        "",
        "### OpenCV RGB-D odometry",
        "",
        *table(HEADER, room + seven, "llrrrrlrll"),
        "",
        f"- {room_note}",
        f"- {seven_note}",
        "- Defaults: frame-to-keyframe with keyframes every 3 cm / 2 deg, images shrunk to "
        "~320 px wide (downscale=2 at 640x480).",
        "",
    ]
    write_text_atomic(RESULTS, "\n".join(lines))
    log.info("wrote %s", RESULTS)
    return 0


if __name__ == "__main__":
    sys.exit(main())
