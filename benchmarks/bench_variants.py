"""LiDAR accuracy on data variants that no single generator setting defines.

    python -m benchmarks.bench_variants [--quick] [--variants NAME ...] [--set KEY=VALUE ...]

Each variant is a generated street along the real KITTI 00 trajectory (``STREETS`` of
benchmarks/harness/kitti.py: seeds, sparse and periodic streets, firings, range noise with
dropouts, and the standard street read with KISS-ICP's KITTI vertical-angle correction), run with
configs/kitti.yaml and KISS-ICP odometry; the odometry columns are KISS-ICP alone on the same
scans, and KISS-SLAM (``benchmarks.harness.reference.kiss_slam``; ``--no-kiss-slam`` skips it) runs
on the same scans read as ours reads them. ``--before-set KEY=VALUE`` runs every variant again with
those overrides, as a "before" row; ``--set`` overrides the run config. Default: the full 4,541
scans; ``--quick``: the quick window of benchmarks.bench_slam (550 scans, 1,024 firings). One table
with per-axis ATE, SLAM's unaligned errors, loops kept, the worst kept loop vs the truth, and the
worst variant per column; accuracy from one run of the window (deterministic), wall time the median
of ``REPEATS`` runs on the first ``TIMING_SCANS`` scans. Writes benchmarks/results/variants.md (and
.json) unless ``--out`` says otherwise. ``--combine A.json B.json ...`` runs nothing: one table
from the results of several invocations, naming each invocation's command, date and machine."""

from __future__ import annotations

import concurrent.futures
import datetime as dt
import itertools
import json
import logging
import multiprocessing
import sys
from pathlib import Path

import numpy as np

from benchmarks.harness.cli import bench_parser, start_logging
from benchmarks.harness.kitti import KITTI_POSES, STREETS, kitti_source
from benchmarks.harness.kitti import window as kitti_window
from benchmarks.harness.machine import machine_line
from benchmarks.harness.paths import RESULTS_DIR
from benchmarks.harness.pipeline import (
    add_override_arguments,
    load_config,
    run_pipeline,
    trajectory_summary,
)
from benchmarks.harness.repeat import REPEATS, Timing, repeats_line
from benchmarks.harness.results import table
from common.atomic_io import write_text_atomic

log = logging.getLogger("benchmarks.bench_variants")


TIMED = "timing_s"
"""The samples of a variant's repeated timing runs, in its results."""
TIMING_SCANS = 100
"""Scans of the repeated timing runs (the accuracy run covers the whole window once)."""
QUICK_VARIANTS = ("periodic", "KITTI angle correction, ideal scans")
"""What ``--quick`` runs unless ``--variants`` says otherwise (the bench-quick budget; two, so
that ``--jobs 2`` runs them side by side): the aliasing street and the worst vertical error."""


def window(quick: bool) -> dict[str, int]:
    """The generated-source window: the harness's quick or full KITTI-00 window."""
    w = kitti_window(quick)
    return {"num_frames": w.num_frames, "step": w.step, "azimuth_steps": w.azimuth_steps}


def _pitch_bias(pipeline, gt: np.ndarray) -> float:
    """Mean pitch error of the odometry between consecutive submap anchors, in mrad per 100 m
    travelled (each anchor's own frame, nose up positive): a bias the pose graph cannot spread
    where no loop ties the stretch."""
    from scipy.spatial.transform import Rotation

    odometry = pipeline.frames.odometry_poses()
    errors, lengths = [], []
    for i, j in itertools.pairwise(pipeline.graph.node_ids):
        a, b = pipeline.frames.submap_frames(i)[0], pipeline.frames.submap_frames(j)[0]
        T_true = np.linalg.inv(gt[a]) @ gt[b]
        T_odometry = np.linalg.inv(odometry[a]) @ odometry[b]
        error = np.linalg.inv(T_true) @ T_odometry
        errors.append(-Rotation.from_matrix(error[:3, :3]).as_rotvec()[1])
        lengths.append(float(np.linalg.norm(T_true[:3, 3])))
    return 1e5 * float(np.sum(errors)) / max(float(np.sum(lengths)), 1e-9)


def _variant_run(quick: bool, name: str, sets: list[str], num_frames: int | None = None):
    """configs/kitti.yaml on the first ``num_frames`` scans of one variant (all by default)."""
    from slam.assembly.config import merge_overrides, set_overrides

    source = kitti_source(quick, num_frames, **STREETS[name])
    overrides = merge_overrides({"source": {"dataset": "generated"}}, set_overrides(sets))
    return (source, *run_pipeline(load_config("kitti", overrides), source))


def run_ours(quick: bool, name: str, sets: list[str]) -> dict:
    """One variant's accuracy (in a child process: one thread, no viewer)."""
    source, pipeline, wall = _variant_run(quick, name, sets)
    gt = source.gt_poses
    r = trajectory_summary(pipeline, gt, wall)
    kept = [(m, d) for m, d, k in r["loop_errors"] if k]
    return {
        "frames": r["frames"],
        "kiss_icp_xyz_m": r["ate_xyz_odometry_m"],
        "kiss_icp_ate_m": r["ate_odometry_m"],
        "slam_xyz_m": r["ate_xyz_slam_m"],
        "slam_ate_m": r["ate_slam_m"],
        "slam_unaligned": r["unaligned_slam"],
        "verified": r["verified"],
        "kept": r["kept"],
        "kept_loop_errors": kept,
        "worst_kept_m": max((m for m, _ in kept), default=0.0),
        "worst_kept_deg": max((d for _, d in kept), default=0.0),
        "pitch_bias_mrad_per_100m": _pitch_bias(pipeline, gt),
        "rejections": r["rejections"],
    }


def time_ours(quick: bool, name: str, sets: list[str]) -> float:
    """Wall seconds of the whole pipeline on the first :data:`TIMING_SCANS` scans of a variant."""
    return _variant_run(quick, name, sets, TIMING_SCANS)[2]


def run_kiss_slam(quick: bool, name: str) -> dict:
    """KISS-SLAM on one variant's scans (its own process, see the module docstring)."""
    from benchmarks.harness.reference import kiss_slam

    return kiss_slam(kitti_source(quick, **STREETS[name]))


def _fmt_xyz(v: list[float]) -> str:
    return " / ".join(f"{x:.2f}" for x in v)


def _fmt_unaligned(r: dict) -> str:
    """SLAM's position RMSE, mean |yaw| and mean tilt in the first pose's frame (results written
    before these columns: '-')."""
    if "slam_unaligned" not in r:
        return "-"
    rmse, yaw, tilt = r["slam_unaligned"]
    return f"{rmse:.2f} / {yaw:.2f} / {tilt:.2f}"


def _kiss_slam_cells(r: dict | None) -> str:
    if r is None:
        return "| not run | | "
    if "skipped" in r:
        return "| skipped | | "
    closures = "?" if r.get("closures") is None else f"{r['closures']:.0f}"
    return f"| {r['ate_slam_m']:.2f} | {_fmt_xyz(r['ate_xyz_slam_m'])} | {closures} "


def _z_ratio(r: dict) -> float:
    """SLAM vertical RMSE over the odometry's."""
    return r["slam_xyz_m"][2] / max(r["kiss_icp_xyz_m"][2], 1e-9)


def _row(name: str, r: dict, kiss_slam: dict | None = None) -> str:
    return (
        f"| {name} | {r['frames']} | {r['kiss_icp_ate_m']:.2f} | {_fmt_xyz(r['kiss_icp_xyz_m'])} "
        f"{_kiss_slam_cells(kiss_slam)}"
        f"| {r['slam_ate_m']:.2f} | {_fmt_xyz(r['slam_xyz_m'])} | {_fmt_unaligned(r)} "
        f"| {r['verified']} | {r['kept']} "
        f"| {r['worst_kept_m']:.2f} / {r['worst_kept_deg']:.2f} "
        f"| {_z_ratio(r):.2f} "
        f"| {r.get('pitch_bias_mrad_per_100m', float('nan')):+.1f} "
        f"| {f'{Timing(r[TIMED]):.1f}' if TIMED in r else '-'} |"
    )


Z_RATIO_TARGET = 0.5
LOOP_TARGET_M = 1.0
LOOP_TARGET_DEG = 1.0


def _targets(name: str, r: dict) -> str:
    z_ratio = _z_ratio(r)
    loops_met = r["worst_kept_m"] <= LOOP_TARGET_M and r["worst_kept_deg"] <= LOOP_TARGET_DEG
    return (
        f"- {name}: z ratio {z_ratio:.2f} ({'met' if z_ratio <= Z_RATIO_TARGET else 'missed'}); "
        f"worst kept loop {r['worst_kept_m']:.2f} m / {r['worst_kept_deg']:.2f} deg "
        f"({'met' if loops_met else 'missed'})"
    )


def new_results(quick: bool, command: str, before_sets: list[str]) -> dict:
    """An invocation's results before any run: what, where and when."""
    return {
        "machine": machine_line(),
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "quick": quick,
        "command": command,
        "before_sets": before_sets,
        "runs": {},
        "before": {},
        "kiss_slam": {},
    }


def combine_results(paths: list[Path]) -> dict:
    """One results dict from the JSON files of several invocations (same window; a variant
    at most once)."""
    parts = [(path, json.loads(Path(path).read_text())) for path in paths]
    if len({part["quick"] for _, part in parts}) != 1:
        raise ValueError("--combine: the files mix --quick and full-length results")
    if len({tuple(part.get("before_sets", [])) for _, part in parts}) != 1:
        raise ValueError("--combine: the files were run with different --before-set overrides")
    names = " ".join(Path(path).name for path, _ in parts)
    combined = new_results(
        parts[0][1]["quick"],
        f"python -m benchmarks.bench_variants --combine {names}",
        parts[0][1].get("before_sets", []),
    )
    combined["sources"] = [
        {"file": Path(path).name, **{k: part[k] for k in ("command", "date", "machine")}}
        for path, part in parts
    ]
    for path, part in parts:
        for kind in ("runs", "before", "kiss_slam"):
            for name, row in part.get(kind, {}).items():
                if name in combined[kind]:
                    raise ValueError(f"--combine: {path}: variant '{name}' is in two files")
                combined[kind][name] = row
    return combined


def write_report(path: Path, results: dict) -> None:
    w = window(results["quick"])
    runs = results["runs"]
    lines = [
        "## LiDAR accuracy on data variants",
        "",
        f"- Command: `{results['command']}`",
        f"- Date: {results['date']}",
        f"- Machine: {results['machine']}",
        *(
            f"- Combined from `{source['file']}`: `{source['command']}`, {source['date']}; "
            f"{source['machine']}"
            for source in results.get("sources", [])
        ),
        "",
        f"Generated 64-beam scans along KITTI 00 frames 0-{(w['num_frames'] - 1) * w['step']}, "
        f"every {w['step']}. ({w['num_frames']} scans, {w['azimuth_steps']} firings unless the "
        "variant says otherwise), configs/kitti.yaml. ATE after SE(3) alignment; x / y / z: RMSE "
        "per world axis (z up). 'SLAM unaligned': in the frame the output files claim (the first "
        "pose the identity), no alignment: position RMSE, mean absolute yaw and mean tilt error. "
        "'worst kept loop': the largest translation / rotation error vs "
        "the truth of the loops the pose graph kept. 'z ratio': SLAM z RMSE / KISS-ICP z RMSE "
        f"(target <= {Z_RATIO_TARGET}). 'pitch bias': KISS-ICP's mean pitch error between "
        "consecutive submap anchors (each anchor's frame, nose up positive) per 100 m "
        "travelled. KISS-SLAM: 0.0.2 with its default config on the same scans; 'closures': "
        "the loop closures it reports. Accuracy: one run each (deterministic). "
        + repeats_line().removeprefix("- ")
        + f" (each a separate run of ours on the variant's first {TIMING_SCANS} scans, two "
        "runs at a time). "
        + (
            f"A 'before' row is ours with `{' '.join(results['before_sets'])}`."
            if results.get("before_sets")
            else ""
        ),
        "",
        *table(
            "variant | scans | KISS-ICP ATE [m] | KISS-ICP x / y / z [m] | KISS-SLAM ATE [m] "
            "| KISS-SLAM x / y / z [m] | KISS-SLAM closures | SLAM ATE [m] | SLAM x / y / z "
            "[m] | SLAM unaligned [m] / yaw / tilt [deg] | verified | kept | worst kept loop "
            f"[m / deg] | z ratio | pitch bias [mrad / 100 m] | wall, first {TIMING_SCANS} "
            "scans [s]",
            [],
        ),
    ]
    kiss = results.get("kiss_slam", {})
    for name, r in runs.items():
        lines.append(_row(name, r, kiss.get(name)))
        if name in results.get("before", {}):
            lines.append(_row(f"{name}, before", results["before"][name], kiss.get(name)))
    if runs:
        lines += ["", "Worst variant per column:", ""]
        columns = {
            "SLAM ATE": lambda r: r["slam_ate_m"],
            "SLAM z RMSE": lambda r: r["slam_xyz_m"][2],
            "SLAM horizontal (x, y) RMSE": lambda r: float(np.hypot(*r["slam_xyz_m"][:2])),
            "z ratio": _z_ratio,
            "worst kept loop [m]": lambda r: r["worst_kept_m"],
            "worst kept loop [deg]": lambda r: r["worst_kept_deg"],
            "fewest loops kept": lambda r: -r["kept"],
        }
        for label, key in columns.items():
            name = max(runs, key=lambda n, k=key: k(runs[n]))
            lines.append(f"- {label}: {name} ({abs(key(runs[name])):.2f})")
        lines += [
            "",
            f"Targets per variant: z ratio <= {Z_RATIO_TARGET}, and every kept loop "
            f"within {LOOP_TARGET_M:.0f} m and {LOOP_TARGET_DEG:.0f} deg of the truth:",
            "",
        ]
        lines += [_targets(name, r) for name, r in runs.items()]
        lines += ["", "Rejected candidates by reason (first word):", ""]
        lines += [f"- {name}: {json.dumps(r['rejections'])}" for name, r in runs.items()]
    lines.append("")
    write_text_atomic(path, "\n".join(lines))


def build_parser():
    quick = f"550 scans (every 3rd), 1024 firings; variants {', '.join(QUICK_VARIANTS)}"
    parser = bench_parser(__doc__, quick, out=RESULTS_DIR / "variants.md")
    parser.add_argument("--variants", nargs="+", choices=list(STREETS))
    add_override_arguments(parser, "'before' row of every variant")
    parser.add_argument("--no-kiss-slam", action="store_true", help="do not run KISS-SLAM")
    parser.add_argument("--jobs", type=int, default=2, help="variants run at a time")
    parser.add_argument(
        "--combine",
        type=Path,
        nargs="+",
        metavar="JSON",
        help="run nothing: one table from these results files",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.combine:
        try:
            results = combine_results(args.combine)
        except (OSError, ValueError) as exc:
            print(exc, file=sys.stderr)
            return 2
        write_text_atomic(args.out.with_suffix(".json"), json.dumps(results, indent=2))
        write_report(args.out, results)
        return 0
    if args.variants is None:
        args.variants = list(QUICK_VARIANTS) if args.quick else list(STREETS)
    start_logging("%(asctime)s %(name)s: %(message)s")
    if not KITTI_POSES.is_file():
        print(f"{KITTI_POSES}: missing; the variants follow KITTI 00's poses", file=sys.stderr)
        return 2
    command = "python -m benchmarks.bench_variants" + (" --quick" if args.quick else "")
    command += "".join(f" --set {s}" for s in args.sets)
    command += "".join(f" --before-set {s}" for s in args.before_sets)
    command += " --no-kiss-slam" if args.no_kiss_slam else ""
    if args.variants != list(QUICK_VARIANTS if args.quick else STREETS):
        command += " --variants " + " ".join(f"'{v}'" for v in args.variants)
    results = new_results(args.quick, command, args.before_sets)
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(args.jobs, mp_context=context) as pool:
        futures = {}
        for v in args.variants:
            futures[("runs", v)] = pool.submit(run_ours, args.quick, v, args.sets)
            for repeat in range(REPEATS):
                futures[("timing", v, repeat)] = pool.submit(time_ours, args.quick, v, args.sets)
            if args.before_sets:
                before = args.sets + args.before_sets
                futures[("before", v)] = pool.submit(run_ours, args.quick, v, before)
            if not args.no_kiss_slam:
                futures[("kiss_slam", v)] = pool.submit(run_kiss_slam, args.quick, v)
        for (kind, name, *_), future in futures.items():
            if kind == "timing":
                results["runs"][name].setdefault(TIMED, []).append(future.result())
                continue
            results[kind][name] = future.result()
            if kind != "kiss_slam":
                log.info("%s %s", kind, _row(name, results[kind][name]))
    write_text_atomic(args.out.with_suffix(".json"), json.dumps(results, indent=2, default=str))
    write_report(args.out, results)
    log.info("wrote %s", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
