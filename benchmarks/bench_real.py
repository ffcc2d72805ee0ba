"""Real LiDAR scans: MulRan Riverside02 keyframes and 22 KITTI raw scans, end to end.

    python -m benchmarks.bench_real [--quick] [--out FILE.md] [--figures DIR]

Every run is ``python -m slam.run lidar FOLDER`` with ``configs/lidar.yaml`` in its own process
(wall time and peak RSS of that process): the MulRan Riverside02 keyframes with ``--odometry gt``
and with KISS-ICP, scored against the reference poses (the first run's mesh also against the scan
points placed by them), and 22 KITTI raw scans (no ground truth) with KISS-ICP: motion per scan,
mesh against the scan points placed by our poses. ``--quick``: the first 100 MulRan keyframes.
Figures go to ``--figures`` (default ``docs/figures``; in quick mode ``benchmarks/out/
real-figures``, so a quick run never replaces the README's). Writes benchmarks/results/real.md
(and .json).
"""

from __future__ import annotations

import json
import logging
import os
import sys
from pathlib import Path

import numpy as np

from benchmarks import real_scores as scores
from benchmarks.harness.child import run_command
from benchmarks.harness.cli import bench_parser
from benchmarks.harness.machine import section_header
from benchmarks.harness.paths import DATA, REPO, RESULTS_DIR, WORK_DIR
from benchmarks.harness.repeat import REPEATS, repeat_runs, repeats_line
from benchmarks.harness.results import table
from common.atomic_io import write_text_atomic

log = logging.getLogger("benchmarks.bench_real")

MULRAN = DATA / "mulran_riverside02_keyframes"
KITTI_RAW = DATA / "kitti_raw_22"
QUICK_FRAMES = "0:100"
MULRAN_KEYFRAMES = 331
PRIOR_FRAMES = 100
PRIOR_FRAMES_QUICK = 60
"""Keyframes of the diagnosis run (KISS-ICP predicted with the reference motion)."""
RUN_TIMEOUT_S = 3600


def _slam_runs(name: str, args: list[str], work: Path) -> dict:
    """``python -m slam.run ARGS``, ``REPEATS`` times, each in its own process: the first run's
    folder and peak RSS, the runs' wall time."""
    folders = iter(work / f"{name}-{k}" for k in range(REPEATS))
    return repeat_runs(lambda: _slam_run(args, next(folders)), ("wall_s",))


def _slam_run(args: list[str], out: Path) -> dict:
    """``python -m slam.run ARGS`` in its own process -> its run folder, wall time, peak RSS."""
    name, work = out.name, out.parent
    if out.exists():
        import shutil

        shutil.rmtree(out)
    paths = [str(REPO), os.environ.get("PYTHONPATH", "")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(paths))
    command = [
        sys.executable,
        "-m",
        "slam.run",
        *args,
        "--no-viz",
        "--no-progress",
        "--out",
        str(out),
    ]
    load_before = os.getloadavg()[0]
    result = run_command(
        command, cwd=REPO, env=env, timeout_s=RUN_TIMEOUT_S, log_file=work / f"{name}.log"
    )
    if result.returncode != 0:
        tail = (work / f"{name}.log").read_text()[-2000:]
        raise RuntimeError(f"{name}: slam.run exited with {result.returncode}:\n{tail}")
    metrics = json.loads((out / "metrics.json").read_text())
    return {
        "folder": out,
        "command": " ".join(["python -m slam.run", *args]),
        "wall_s": result.usage.wall_s,
        "peak_rss_mb": result.usage.peak_rss_mb,
        "load": 0.5 * (load_before + os.getloadavg()[0]),
        "frames": metrics.get("num_frames"),
        "loops_kept": metrics["loops"]["graph_inliers"],
    }


def _poses(folder: Path, kind: str) -> np.ndarray:
    from slam.run_folder.trajectory_io import read_kitti

    return read_kitti(folder / f"poses_{kind}.kitti.txt")


def run_benchmark(quick: bool, figures: Path, work: Path) -> dict:
    from frontends.sources.kitti import read_kitti_poses
    from frontends.sources.pcd_folder import pcd_scan_files

    work.mkdir(parents=True, exist_ok=True)
    frames = ["--frames", QUICK_FRAMES] if quick else []
    gt_file = MULRAN / "optimized_poses.txt"
    mulran_args = ["lidar", str(MULRAN / "scans"), "--set", f"source.lidar.gt_poses={gt_file}"]
    runs = {
        "mulran-gt": _slam_runs("mulran-gt", [*mulran_args, *frames, "--odometry", "gt"], work),
        "mulran-kiss": _slam_runs("mulran-kiss", [*mulran_args, *frames], work),
        "kitti-raw-kiss": _slam_runs("kitti-raw-kiss", ["lidar", str(KITTI_RAW)], work),
    }
    count = 100 if quick else MULRAN_KEYFRAMES
    reference = read_kitti_poses(gt_file)[:count]
    fastlio_odometry = read_kitti_poses(MULRAN / "odom_poses.txt")[:count]
    mulran_files = pcd_scan_files(MULRAN / "scans")[:count]

    results: dict = {"quick": quick, "runs": {}, "mulran_keyframes": count}
    for name in ("mulran-gt", "mulran-kiss"):
        run = runs[name]
        folder = run["folder"]
        run["odometry"] = scores.tracking_scores(_poses(folder, "odometry"), reference)
        run["slam"] = scores.tracking_scores(_poses(folder, "slam"), reference)
    results["fastlio_odometry"] = scores.tracking_scores(fastlio_odometry, reference)

    # Diagnosis: the same registration with the reference motion as its prediction.
    n = min(PRIOR_FRAMES_QUICK if quick else PRIOR_FRAMES, count)
    kiss_folder = runs["mulran-kiss"]["folder"]
    prior_poses = scores.kiss_icp_with_reference_prediction(
        mulran_files[:n], reference[:n], kiss_folder / "config.yaml"
    )
    cv_error = scores.constant_velocity_error(reference)
    results["diagnosis"] = {
        "frames": n,
        "reference_prediction": scores.tracking_scores(prior_poses, reference[:n]),
        "constant_velocity": scores.tracking_scores(
            _poses(kiss_folder, "odometry")[:n], reference[:n]
        ),
        "cv_error_median_m": float(np.median(cv_error)),
        "cv_error_p90_m": float(np.percentile(cv_error, 90)),
        "cv_error_above_2m": int(np.count_nonzero(cv_error > 2.0)),
        "cv_predictions": len(cv_error),
        "spacing_median_m": float(
            np.median(np.linalg.norm(np.diff(reference[:, :3, 3], axis=0), axis=1))
        ),
    }

    # The run's world frame is its first pose: the mesh lies in the frame of poses_slam, which
    # with --odometry gt are the reference poses re-anchored there.
    gt_folder = runs["mulran-gt"]["folder"]
    mesh_poses = _poses(gt_folder, "slam")
    points = scores.map_points(mulran_files, mesh_poses, gt_folder / "config.yaml")
    gt_mesh = scores.mesh_point_distances(gt_folder / "mesh.ply", points)
    runs["mulran-gt"]["mesh"] = gt_mesh

    raw = runs["kitti-raw-kiss"]
    raw_poses = _poses(raw["folder"], "odometry")
    raw["steps"] = scores.step_statistics(raw_poses)
    raw_config = raw["folder"] / "config.yaml"
    raw_points = scores.map_points(pcd_scan_files(KITTI_RAW), raw_poses, raw_config)
    raw_mesh = scores.mesh_point_distances(raw["folder"] / "mesh.ply", raw_points)
    raw["mesh"] = raw_mesh

    from benchmarks.real_figures import write_real_figures

    results["figures"] = [
        str(p.relative_to(REPO) if p.is_relative_to(REPO) else p)
        for p in write_real_figures(
            figures,
            mulran={
                "reference": reference,
                "fastlio": fastlio_odometry,
                "kiss": _poses(runs["mulran-kiss"]["folder"], "odometry"),
                "kiss_slam": _poses(runs["mulran-kiss"]["folder"], "slam"),
                "diagnosis": prior_poses,
                "mesh": gt_folder / "mesh.ply",
                "mesh_poses": mesh_poses,
                "distances": gt_mesh.pop("vertex_distances_m"),
            },
            kitti_raw={
                "poses": raw_poses,
                "mesh": raw["folder"] / "mesh.ply",
                "distances": raw_mesh.pop("vertex_distances_m"),
            },
        )
    ]
    for run in runs.values():
        run["folder"] = str(run["folder"])
    results["runs"] = runs
    return results


def _traj_row(name: str, s: dict, run: dict | None) -> list:
    cost = ["-"] * 3
    if run:
        cost = [f"{run['wall_s']:.0f}", f"{run['peak_rss_mb']:.0f}", f"{run['load']:.1f}"]
    return [
        name,
        s["steps"] + 1,
        f"{s['ate_m']:.2f}",
        " / ".join(f"{v:.2f}" for v in s["ate_xyz_m"]),
        f"{s['est_length_m']:.0f} / {s['length_m']:.0f}",
        f"{s['steps_lost']} / {s['steps']}",
        *cost,
    ]


def _traj_table(first_column: str, rows: list[list]) -> list[str]:
    header = (
        f"{first_column} | poses | ATE (m) | x / y / z RMSE (m) | path est / ref (m) | "
        "steps off by > 1 m | wall (s) | peak RSS (MB) | load"
    )
    return table(header, rows, "lrrlrrrrr")


def _mesh_row(name: str, m: dict) -> list:
    cells = [name, m["vertices"]]
    for side, near in (("vertex_to_points", "vertices_near"), ("points_to_mesh", "points_near")):
        cells += [f"{m[f'{side}_{q}_m']:.3f}" for q in ("median", "p90")]
        cells.append(f"{100 * m[near]:.1f} %")
    return cells


def write_report(path: Path, results: dict, command: str) -> None:
    runs = results["runs"]
    gt, kiss, raw = runs["mulran-gt"], runs["mulran-kiss"], runs["kitti-raw-kiss"]
    steps = raw["steps"]
    diag = results["diagnosis"]
    count = results["mulran_keyframes"]
    which = "all 331" if count == MULRAN_KEYFRAMES else f"the first {count} of 331"
    lines = [
        *section_header("Real LiDAR scans", command),
        "",
        f"MulRan Riverside02: {which} Ouster OS1-64 keyframes (median 5.7 m apart, 0.1-45 m), "
        "scored against the reference poses "
        "(`optimized_poses.txt`: FAST-LIO2 + Scan Context loop closure, another system's "
        "estimate, decimetre-level). KITTI raw: 22 consecutive HDL-64E scans at 10 Hz, no ground "
        "truth. Every run: `python -m slam.run lidar FOLDER` with configs/lidar.yaml "
        "(scale derived from the first scan), one process each; wall time and peak RSS of that "
        "process, load = 1-minute load average during the run. "
        + repeats_line(
            "Each `slam.run` runs that often; its accuracy, mesh and peak RSS are the first "
            "run's (the same in every run)."
        ).removeprefix("- "),
        "",
        *_traj_table(
            "MulRan trajectory",
            [
                _traj_row("`--odometry gt` (reference poses), SLAM", gt["slam"], gt),
                _traj_row("KISS-ICP odometry", kiss["odometry"], kiss),
                _traj_row(
                    f"KISS-ICP + loops, SLAM ({kiss['loops_kept']} loops kept)", kiss["slam"], None
                ),
                _traj_row(
                    "FAST-LIO2 odometry (`odom_poses.txt`, no run)",
                    results["fastlio_odometry"],
                    None,
                ),
            ],
        ),
        "",
        f"KISS-ICP on the keyframes: {kiss['odometry']['steps_lost']} of "
        f"{kiss['odometry']['steps']} scan-to-scan motions are more than 1 m off the reference's "
        f"(median error {kiss['odometry']['step_error_median_m']:.2f} m; the motions it gets "
        f"wrong have a median length of {kiss['odometry']['lost_step_median_length_m']:.1f} m, "
        f"those it gets right {kiss['odometry']['kept_step_median_length_m']:.1f} m).",
        "",
        f"Why: the same KISS-ICP registration (the run's settings) on the first "
        f"{diag['frames']} keyframes, once with its constant-velocity prediction (the run) and "
        "once predicted with the reference's own motion:",
        "",
        *_traj_table(
            "first keyframes",
            [
                _traj_row(
                    "constant-velocity prediction (the run)", diag["constant_velocity"], None
                ),
                _traj_row("prediction = reference motion", diag["reference_prediction"], None),
            ],
        ),
        "",
        f"Over the {diag['cv_predictions'] + 2} keyframes of the runs (median spacing "
        f"{diag['spacing_median_m']:.1f} m), the constant-velocity prediction lands a median "
        f"{diag['cv_error_median_m']:.2f} m from the reference pose (90th percentile "
        f"{diag['cv_error_p90_m']:.1f} m; {diag['cv_error_above_2m']} of "
        f"{diag['cv_predictions']} more than 2 m off, KISS-ICP's initial threshold).",
        "",
        "ATE: RMSE of the positions after an SE(3) alignment; path est / ref: length of the "
        "estimated and of the reference path; steps off: scan-to-scan motions whose "
        "translation differs from the reference's by more than 1 m.",
        "",
        "Mesh against the scan points it was built from (the points between "
        "`submaps.min_range_m` and `submaps.max_range_m` of each scan, placed by the run's "
        f"poses): vertex -> nearest point, and point -> mesh surface ({MAX_QUERIES_LABEL}); "
        "'near' is within 0.5 m (half the MulRan map voxel).",
        "",
        *table(
            "mesh | vertices | vertex->points median (m) | p90 (m) | vertices near | "
            "points->mesh median (m) | p90 (m) | points near",
            [
                _mesh_row("MulRan, reference poses", gt["mesh"]),
                _mesh_row("KITTI raw 22 scans, KISS-ICP poses", raw["mesh"]),
            ],
            "lrrrrrrr",
        ),
        "",
        f"KITTI raw, KISS-ICP: {steps['scans']} scans, motion per scan median "
        f"{steps['step_median_m']:.3f} m (min {steps['step_min_m']:.3f}, max "
        f"{steps['step_max_m']:.3f}; largest change between consecutive scans "
        f"{steps['step_change_max_m']:.3f} m), largest yaw per scan "
        f"{steps['yaw_abs_max_deg']:.2f} deg, {steps['path_m']:.1f} m in all; "
        f"{raw['loops_kept']} loops (none expected); wall {raw['wall_s']:.0f} s, "
        f"peak RSS {raw['peak_rss_mb']:.0f} MB, load {raw['load']:.1f}.",
        "",
        "Figures: " + ", ".join(f"`{p}`" for p in results["figures"]),
        "",
    ]
    write_text_atomic(path, "\n".join(lines))
    write_text_atomic(path.with_suffix(".json"), json.dumps(results, indent=1, default=str))


MAX_QUERIES_LABEL = "a seeded subset of 50,000 points"


def build_parser():
    parser = bench_parser(__doc__, "the first 100 MulRan keyframes", out=RESULTS_DIR / "real.md")
    parser.add_argument("--figures", type=Path, help="figure folder (see the module docstring)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    command = "python -m benchmarks.bench_real" + (" --quick" if args.quick else "")
    command = os.environ.get("BENCH_INVOKED_AS", command)
    if not (MULRAN / "scans").is_dir() or not KITTI_RAW.is_dir():
        log.warning("real scans not found under %s; bench_real skipped", DATA)
        lines = section_header("Real LiDAR scans", command)
        skipped = [*lines, "", f"Skipped: no real scans under {DATA}.", ""]
        write_text_atomic(args.out, "\n".join(skipped))
        return 0
    figures = args.figures or (WORK_DIR / "real-figures" if args.quick else REPO / "docs/figures")
    results = run_benchmark(args.quick, figures, WORK_DIR / "real")
    write_report(args.out, results, command)
    log.info("wrote %s", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
