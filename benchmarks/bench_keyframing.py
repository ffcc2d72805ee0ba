"""Keyframing cost per LiDAR scan: ``Keyframer.add`` on generated KITTI-00 scans.

    python -m benchmarks.bench_keyframing [--frames N] [--before REV] [--quick]

The first N scans of benchmarks.harness.kitti's sequence (``--quick``: of the quick window) with
their ground-truth poses go to a :class:`slam.algorithm.submaps.Keyframer` with
``configs/kitti.yaml``'s settings, alone in a process with one BLAS thread. Reported: the calling
thread's CPU time per frame, for frames that only accumulate and frames that close a submap, and
what was closed (two revisions must produce the same map). ``REPEATS`` processes per revision;
``--before REV`` measures REV too, checked out beside this tree.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import sys
import time

import numpy as np

from benchmarks.bench_throughput import _config
from benchmarks.harness.checkout import revisions
from benchmarks.harness.child import UnsupportedRevision, in_child
from benchmarks.harness.cli import bench_parser, command_line, start_logging
from benchmarks.harness.kitti import kitti_source, window
from benchmarks.harness.machine import machine_line
from benchmarks.harness.paths import RESULTS_DIR
from benchmarks.harness.repeat import repeat_runs, repeats_line
from benchmarks.harness.results import table
from common.atomic_io import write_text_atomic

RESULTS = RESULTS_DIR / "keyframing.json"
REPORT = RESULTS_DIR / "keyframing.md"
QUICK_FRAMES = 120
TIMING_KEYS = ("cpu_ms_per_frame", "accumulate_cpu_ms_median", "close_cpu_ms_mean")

log = logging.getLogger("benchmarks.bench_keyframing")


def measure(quick: bool, num_frames: int) -> dict:
    from threadpoolctl import threadpool_limits

    from slam.algorithm.submaps import Keyframer

    threadpool_limits(limits=1, user_api="blas")
    cfg = _config()
    keyframer = Keyframer(cfg.submaps)
    accumulate_ms, close_ms, closed, points = [], [], [], []
    T_W0_W = None
    load = os.getloadavg()[0]
    for frame in kitti_source(quick, num_frames):  # streamed: 500 scans are 1.5 GB
        if T_W0_W is None:
            T_W0_W = np.linalg.inv(frame.T_W_S_gt)
        points.append(len(frame.points))
        start = time.thread_time()
        record, _, _ = keyframer.add(frame, T_W0_W @ frame.T_W_S_gt)
        elapsed_ms = 1e3 * (time.thread_time() - start)
        (close_ms if record is not None else accumulate_ms).append(elapsed_ms)
        if record is not None:
            closed.append(record)
    start = time.thread_time()
    closed.append(keyframer.finish())
    close_ms.append(1e3 * (time.thread_time() - start))
    total_ms = sum(accumulate_ms) + sum(close_ms)
    return {
        "frames": len(points),
        "points_per_frame": float(np.mean(points)),
        "cpu_ms_per_frame": total_ms / len(points),
        "accumulate_cpu_ms_median": float(np.median(accumulate_ms)),
        "close_cpu_ms_mean": float(np.mean(close_ms)),
        "submaps": len(closed),
        "map_points": int(sum(len(r.points_A) for r in closed)),
        "loop_points": int(sum(len(r.loop_points_A) for r in closed)),
        "load_start": load,
        "load_end": os.getloadavg()[0],
        "date": dt.datetime.now().isoformat(timespec="seconds"),
    }


def write_report(saved: dict) -> None:
    lines = [
        "## Keyframing per LiDAR scan",
        "",
        f"- Command: `{saved['command']}`",
        f"- Machine: {saved['machine']}",
        "",
        f"`Keyframer.add` on {window(saved['quick']).describe(saved['frames'])} with "
        "ground-truth poses, `configs/kitti.yaml` submap settings, one thread; CPU time of that "
        "thread. *close* includes compaction, normals and the loop cloud of the closed submap.",
        repeats_line(deterministic="Submaps and map points are the same in every run."),
        "",
    ]
    lines += table(
        "code | date | load | points/scan | ms/frame | accumulate median ms | close "
        "mean ms | submaps | map points",
        [],
    )
    for key, r in saved["runs"].items():
        if "unsupported" in r:
            lines.append(f"| {key} | {r['unsupported']} |||||||")
            continue
        cells = [
            key,
            r["date"],
            f"{r['load_start']:.1f}-{r['load_end']:.1f}",
            f"{r['points_per_frame']:.0f}",
            f"{r['cpu_ms_per_frame']:.1f}",
            f"{r['accumulate_cpu_ms_median']:.1f}",
            f"{r['close_cpu_ms_mean']:.0f}",
            r["submaps"],
            r["map_points"],
        ]
        lines.append("| " + " | ".join(map(str, cells)) + " |")
    write_text_atomic(REPORT, "\n".join(lines) + "\n")


def build_parser():
    parser = bench_parser(__doc__, f"the first {QUICK_FRAMES} scans", before=True)
    parser.add_argument("--frames", type=int, default=500, help="first N scans")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.quick:
        args.frames = min(args.frames, QUICK_FRAMES)
    start_logging("%(asctime)s %(name)s: %(message)s")
    saved = {
        "command": command_line("bench_keyframing", argv),
        "machine": machine_line(),
        "quick": args.quick,
        "frames": args.frames,
        "runs": {},
    }
    with revisions(args.before) as codes:
        for label, code in codes.items():
            try:
                saved["runs"][label] = repeat_runs(
                    lambda code=code: in_child(measure, args.quick, args.frames, code=code),
                    TIMING_KEYS,
                )
            except UnsupportedRevision as error:
                saved["runs"][label] = {"unsupported": str(error)}
            log.info("%s: %s", label, saved["runs"][label])
    write_text_atomic(RESULTS, json.dumps(saved, indent=2))
    write_report(saved)
    return 0


if __name__ == "__main__":
    sys.exit(main())
