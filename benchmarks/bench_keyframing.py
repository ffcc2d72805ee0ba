"""Keyframing cost per LiDAR scan: ``Keyframer.add`` on generated KITTI-00 scans (issue 11).

    python -m benchmarks.bench_keyframing [--frames N] [--label after] [--quick] [--code DIR]

Feeds the first N scans of the generated 64-beam KITTI-00 sequence (the same cached scans as
``bench_throughput``, ~127k points each) with their ground-truth poses to a
:class:`slam.algorithm.submaps.Keyframer` with ``configs/kitti.yaml``'s submap settings, alone in
this
process with one BLAS thread, as the pipeline runs it. Reports the CPU time of the calling thread
(``time.thread_time``, so other processes on the machine inflate it less than wall time) per
frame, split into frames that only accumulate and frames that also close a submap (compaction,
normals, loop cloud), and what was closed (submaps, map points), so that two labels can be checked
to produce the same map.

Results accumulate in ``benchmarks/results/keyframing.json`` under ``--label``; ``--code DIR``
imports ``slam`` and ``frontends`` from another checkout (e.g. ``git worktree add /tmp/base
<commit>``) to measure that code; the report ``benchmarks/results/keyframing.md`` shows all
labels.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import sys
import time

import numpy as np

from benchmarks.bench_throughput import _config, _source

REPO_RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
RESULTS = os.path.join(REPO_RESULTS, "keyframing.json")
REPORT = os.path.join(REPO_RESULTS, "keyframing.md")
QUICK_FRAMES = 120

log = logging.getLogger("benchmarks.bench_keyframing")


def measure(num_frames: int) -> dict:
    from threadpoolctl import threadpool_limits

    from slam.algorithm.submaps import Keyframer

    threadpool_limits(limits=1, user_api="blas")
    cfg = _config()
    keyframer = Keyframer(cfg.submaps)
    accumulate_ms, close_ms, closed, points = [], [], [], []
    T_W0_W = None
    load = os.getloadavg()[0]
    for frame in _source(num_frames):  # streamed: 500 scans are 1.5 GB
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
    }


def write_report(results: dict) -> None:
    lines = [
        "## Keyframing per LiDAR scan",
        "",
        "`python -m benchmarks.bench_keyframing --frames N --label L`: `Keyframer.add` on the "
        "first N generated KITTI-00 scans with ground-truth poses, `configs/kitti.yaml` submap "
        "settings, one thread; CPU time of that thread. *close* includes compaction, normals "
        "and the loop cloud of the closed submap.",
        "",
        "| run | date | load | points/scan | ms/frame | accumulate median ms | close mean ms "
        "| submaps | map points |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key in sorted(results):
        r = results[key]
        lines.append(
            f"| {key} | {r['date']} | {r['load_start']:.1f}-{r['load_end']:.1f} "
            f"| {r['points_per_frame']:.0f} | {r['cpu_ms_per_frame']:.1f} "
            f"| {r['accumulate_cpu_ms_median']:.1f} | {r['close_cpu_ms_mean']:.0f} "
            f"| {r['submaps']} | {r['map_points']} |"
        )
    with open(REPORT, "w") as stream:
        stream.write("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=500, help="first N scans")
    parser.add_argument("--label", default="after", help="code label of this run")
    parser.add_argument("--quick", action="store_true", help=f"the first {QUICK_FRAMES} scans")
    parser.add_argument("--code", help="checkout whose slam/ and frontends/ to measure")
    args = parser.parse_args(argv)
    if args.code:
        sys.path.insert(0, os.path.abspath(args.code))  # before anything imports slam
    if args.quick:
        args.frames = min(args.frames, QUICK_FRAMES)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    run = measure(args.frames)
    run["date"] = dt.datetime.now().isoformat(timespec="seconds")
    import slam

    run["code"] = os.path.dirname(os.path.dirname(os.path.abspath(slam.__file__)))
    log.info("%s", run)
    results = {}
    if os.path.isfile(RESULTS):
        with open(RESULTS) as stream:
            results = json.load(stream)
    results[f"{args.frames} frames, {args.label}"] = run
    with open(RESULTS, "w") as stream:
        json.dump(results, stream, indent=2)
    write_report(results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
