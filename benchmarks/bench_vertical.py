"""LiDAR vertical drift: per-axis ATE of KISS-ICP alone and of the SLAM, with and without relief.

    python -m benchmarks.bench_vertical [--quick] [--relief 0 4] [--out FILE.md]

The generated street along the real KITTI 00 trajectory (``benchmarks.bench_slam``'s LiDAR window:
frames 0-1699, or every 3rd frame of 0-1650 with 1024 firings per revolution in quick mode). The
road always follows KITTI 00's elevations; ``--relief`` lists the heights of the hills beside the
road (``generated.terrain_relief_m``) to run. configs/kitti.yaml, KISS-ICP odometry; each run in
its own process (two at a time), once as configured and once with
``odometry.ground_refinement.enabled``
(slam/algorithm/ground_refinement.py: each scan's height, roll and
pitch fitted to the ground seen over the last 50 m of travel); ``--modes`` adds the unbounded
ground map of stop 16. Per-axis ATE: RMSE along the world x, y, z (up) axes
after the SE(3) alignment.
Writes benchmarks/results/vertical.md (and .json) unless ``--out`` says otherwise.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import logging
import multiprocessing
import os
import sys
from pathlib import Path

from benchmarks.bench_slam import lidar_frames, scenario_lidar
from benchmarks.harness.kitti import window
from benchmarks.harness.machine import machine_line
from benchmarks.harness.paths import RESULTS_DIR
from common.atomic_io import write_text_atomic

log = logging.getLogger("benchmarks.bench_vertical")


def _row(name: str, r: dict) -> str:
    od, sl = r["ate_xyz_odometry_m"], r["ate_xyz_slam_m"]
    return (
        f"| {name} | {r['frames']} | {r['kept']} | {r['ate_odometry_m']:.3f} | "
        f"{od[0]:.3f} / {od[1]:.3f} / {od[2]:.3f} | {r['ate_slam_m']:.3f} | "
        f"{sl[0]:.3f} / {sl[1]:.3f} / {sl[2]:.3f} | {r['fps']:.2f} | {r['load']:.1f} |"
    )


MODES: dict[str, dict | None] = {
    "KISS-ICP": None,
    "KISS-ICP + ground refinement": {"ground_refinement": {"enabled": True}},
    # the ground map of stop 16, which kept every cell: a revisit snapped onto the first visit
    "KISS-ICP + ground refinement, unbounded ground map": {
        "ground_refinement": {"enabled": True, "memory_m": None}
    },
}


def _name(relief_m: float, mode: str) -> str:
    return f"{relief_m:g} m hills, {mode}"


def _timed_run(quick: bool, relief_m: float, mode: str) -> dict:
    load = os.getloadavg()[0]
    run = scenario_lidar(quick, "kiss-icp", relief_m, MODES[mode])
    run["load"] = 0.5 * (load + os.getloadavg()[0])
    return run


def write_report(path: Path, results: dict) -> None:
    quick = results["quick"]
    lines = [
        "## LiDAR vertical drift (issue 12)",
        "",
        f"- Command: `{results['command']}`",
        f"- Machine: {results['machine']}",
        "",
        "Generated HDL-64E-like scans along "
        f"{window(quick).describe(lidar_frames(quick))}; the road follows KITTI 00's real "
        "elevations (slopes, crests, dips; the "
        "ground under the car is the trajectory's height minus 1.73 m), and hills of the given "
        "height rise beside it. configs/kitti.yaml, without and with "
        "`odometry.ground_refinement` (each scan's height, roll and pitch fitted to a map of the "
        "ground seen over the last `memory_m` = 50 m of travel; 'unbounded': every cell kept, "
        "as before stop 19). ATE after SE(3) alignment; x / y / z: RMSE along each world axis "
        "(z up). The odometry columns of the KISS-ICP rows are KISS-ICP alone. Two runs at a "
        "time on a shared machine: frames/s is indicative only.",
        "",
        "| street, odometry | frames | loops kept | ATE odometry [m] | x / y / z [m] "
        "| ATE SLAM [m] | x / y / z [m] | frames/s | load |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [_row(name, r) for name, r in results["runs"].items()]
    lines.append("")
    write_text_atomic(path, "\n".join(lines))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="every 3rd frame, 1024 firings")
    parser.add_argument(
        "--relief",
        type=float,
        nargs="+",
        help="hill heights to run (default 0 and 4 m; with --quick 0 m only: its scans are cached)",
    )
    parser.add_argument(
        "--modes",
        nargs="+",
        choices=list(MODES),
        default=list(MODES)[:2],
        help="odometry variants to run (default: KISS-ICP with and without ground refinement)",
    )
    parser.add_argument("--out", type=Path, default=RESULTS_DIR / "vertical.md")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.relief is None:
        args.relief = [0.0] if args.quick else [0.0, 4.0]
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    command = "python -m benchmarks.bench_vertical" + (" --quick" if args.quick else "")
    command += " --relief " + " ".join(f"{r:g}" for r in args.relief)
    if args.modes != list(MODES)[:2]:
        command += " --modes " + " ".join(f"'{m}'" for m in args.modes)
    results: dict = {
        "machine": machine_line(),
        "quick": args.quick,
        "command": command,
        "runs": {},
    }
    jobs = [(relief, mode) for relief in args.relief for mode in args.modes]
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(max_workers=2, mp_context=context) as pool:
        futures = [pool.submit(_timed_run, args.quick, relief, mode) for relief, mode in jobs]
        for (relief, mode), future in zip(jobs, futures, strict=True):
            name = _name(relief, mode)
            results["runs"][name] = future.result()
            log.info("%s", _row(name, results["runs"][name]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out.with_suffix(".json"), json.dumps(results, indent=2, default=str))
    write_report(args.out, results)
    log.info("wrote %s", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
