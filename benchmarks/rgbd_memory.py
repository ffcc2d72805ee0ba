"""RGB-D memory and throughput: the demo and 7-Scenes 0-399, with a per-object breakdown.

    python -m benchmarks.rgbd_memory [--before REV] [--only demo|7scenes]

Each run is ``slam.run``'s pipeline without a viewer (configs/demo.yaml: the generated room,
240 frames; configs/7scenes.yaml on redkitchen seq-01 frames 0-399, skipped without the data),
in its own process so its peak RSS is its own: frames from the source's read-ahead, the final
optimisation and the final mesh. The RSS is broken down (:mod:`benchmarks.memory_breakdown`)
every 100 frames, after the last frame and at the end; the report shows the sample with the
highest RSS, the last frame's and the end's. ``--before REV`` runs revision REV's code (checked
out beside this tree) first, in the same invocation. The final mesh runs on the thread budget's
mesh threads, as in ``slam.run``. Writes ``benchmarks/results/rgbd_memory.json`` and ``.md``
(``--report-only``: the ``.md`` again from the ``.json``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks.harness.checkout import checkout
from benchmarks.harness.child import in_child
from benchmarks.harness.machine import machine_line
from benchmarks.harness.paths import DATA, RESULTS_DIR
from common.atomic_io import write_text_atomic

RESULTS = RESULTS_DIR / "rgbd_memory.json"
SAMPLE_EVERY = 100
SCENARIOS = ("demo", "7scenes")

log = logging.getLogger("benchmarks.rgbd_memory")


def _config(name: str):
    from slam.assembly.config import default_config_path, load_run_config

    overrides: dict[str, Any] = {
        "viz": {"mode": "none", "mesh_every_submaps": 10**9, "mesh_after_remap": False},
        "mapping": {"device": "cpu"},
    }
    if name == "7scenes":
        overrides["source"] = {
            "root": str(DATA / "7scenes_redkitchen"),
            "sequence": "seq-01",
            "frames": "0:400",
        }
    return load_run_config(default_config_path(name), overrides)


def scenario(name: str) -> dict | None:
    """One RGB-D run with its breakdowns (in a child process)."""
    logging.basicConfig(level=logging.WARNING)
    if name == "7scenes" and not (DATA / "7scenes_redkitchen").is_dir():
        return None
    from benchmarks.memory_breakdown import buffer_bytes, memory_breakdown, rss_mb, trim_mb
    from frontends.sources import make_source
    from slam.algorithm.pipeline import SlamPipeline
    from slam.assembly.builders import build_map, build_odometry, source_kwargs
    from slam.assembly.threads import apply_thread_budget, plan_thread_budget
    from slam.evaluation.metrics.trajectory import ate_rmse

    cfg = _config(name)
    threads = apply_thread_budget(cfg).describe()
    source = make_source(cfg.source.dataset, **source_kwargs(cfg))
    pipeline = SlamPipeline(
        cfg.pipeline_config(), source.sensor, build_odometry(cfg, "rgbd"), build_map(cfg)
    )
    baseline = rss_mb()[0]
    samples: dict[str, dict[str, float]] = {}
    instrument_s = 0.0
    count = 0
    start = time.perf_counter()
    queued = 0
    for frame in source.read_ahead():
        pipeline.process(frame)
        queued = max(queued, len(pipeline.submap_worker._pending))
        count += 1
        if count % SAMPLE_EVERY == 0:
            mark = time.perf_counter()
            ahead = {"source_read_ahead_2_more": 2 * buffer_bytes(frame) / 1e6}
            samples[str(count)] = memory_breakdown(pipeline, baseline, [frame], None, ahead)
            instrument_s += time.perf_counter() - mark
    frames_peak = rss_mb()[1]
    detector = pipeline.loop_detector
    kept_keyframes = len(getattr(detector, "_features", {}))
    mark = time.perf_counter()
    last = memory_breakdown(pipeline, baseline)
    instrument_s += time.perf_counter() - mark
    pipeline.finish()
    mesh_threads = plan_thread_budget(cfg.threads, cfg.map_worker).mesh_threads
    mesh = pipeline.map.extract_mesh(threads=mesh_threads)
    wall = time.perf_counter() - start - instrument_s
    peak = rss_mb()[1]
    finished = memory_breakdown(pipeline, baseline)
    finished["trim_returned"] = trim_mb() or float("nan")
    gt = source.gt_poses
    verified = pipeline.accepted_loops()
    return {
        "frames": count,
        "fps": count / wall,
        "wall_s": wall,
        "peak_rss_mb": peak,
        "peak_rss_frames_mb": frames_peak,
        "baseline_mb": baseline,
        "ate_odometry_m": ate_rmse(pipeline.odometry_poses(), gt),
        "ate_slam_m": ate_rmse(pipeline.slam_poses(), gt),
        "submaps": len(pipeline.submaps),
        "candidates": len(pipeline.loop_candidates),
        "verified": len(verified),
        "kept": sum(1 for c in verified if c.graph_inlier),
        "loops": [
            [c.reference_id, c.query_id, c.detector, [float(v) for v in c.T_Ai_Aj[:3].ravel()]]
            for c in verified
        ],
        "kept_keyframes": kept_keyframes,
        "max_submap_worker_jobs": queued,
        "mesh_faces": len(mesh.faces),
        "threads": threads,
        "samples": samples,
        "last_frame": last,
        "finished": finished,
        "load": os.getloadavg()[0],
    }


def _largest(run: dict) -> dict[str, float]:
    """The breakdown sample with the highest RSS."""
    samples = list(run["samples"].values()) or [run["finished"]]
    return max(samples, key=lambda s: s["rss"])


def _columns(run: dict) -> tuple[dict, dict, dict]:
    """The breakdowns shown: the largest sample, the last frame's (before ``finish``) and the
    one after the final mesh."""
    return _largest(run), run.get("last_frame", {}), run["finished"]


def table(saved: dict) -> str:
    rows = [
        "| run | code | frames/s | peak RSS [MB] | of which frames [MB] | ATE odometry [m] | "
        "ATE SLAM [m] | loops verified / kept | keyframes kept at the last frame | "
        "most frames queued | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in SCENARIOS:
        for label, runs in saved["runs"].items():
            r = runs.get(name)
            if not r or "frames" not in r:
                rows.append(f"| {name} | {label} | {r} |" + " |" * 8)
                continue
            rows.append(
                f"| {name} ({r['frames']} frames) | {label} | {r['fps']:.2f} | "
                f"{r['peak_rss_mb']:.0f} | {r['peak_rss_frames_mb']:.0f} | "
                f"{r['ate_odometry_m']:.5f} | {r['ate_slam_m']:.5f} | "
                f"{r['verified']} / {r['kept']} | {r['kept_keyframes']} | "
                f"{r.get('max_submap_worker_jobs')} | {r['load']:.1f} |"
            )
    out = ["\n".join(rows)]
    for name in SCENARIOS:
        labels = [label for label, runs in saved["runs"].items() if runs.get(name)]
        if not labels:
            continue
        keys: list[str] = []
        for label in labels:
            for which in (
                _largest(saved["runs"][label][name]),
                saved["runs"][label][name]["finished"],
            ):
                keys += [k for k in which if k not in keys]
        head = " | ".join(
            f"{label}: largest sample | {label}: last frame | {label}: end" for label in labels
        )
        lines = [f"| {name} [MB] | {head} |", "|---" * (1 + 3 * len(labels)) + "|"]
        for key in keys:
            cells = []
            for label in labels:
                r = saved["runs"][label][name]
                for which in _columns(r):
                    value = which.get(key)
                    cells.append("" if value is None else f"{value:.1f}")
            lines.append(f"| {key} | " + " | ".join(cells) + " |")
        out.append("\n".join(lines))
    return "\n\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", metavar="REV", help="also run revision REV's code, first")
    parser.add_argument("--only", choices=SCENARIOS, action="append")
    parser.add_argument("--report-only", action="store_true", help="print the table of the .json")
    args = parser.parse_args(argv)
    if args.report_only:
        _write(json.loads(RESULTS.read_text()))
        return 0
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    shown = sys.argv[1:] if argv is None else argv
    saved: dict[str, Any] = {
        "command": " ".join(["python", "-m", "benchmarks.rgbd_memory", *shown]),
        "machine": machine_line(),
        "runs": {},
    }
    with contextlib.ExitStack() as stack:
        codes: dict[str, Path | None] = {}
        if args.before:
            codes[f"before {args.before}"] = stack.enter_context(checkout(args.before))
        codes["after"] = None
        for name in args.only or SCENARIOS:
            for label, code in codes.items():
                log.info("%s (%s)", name, label)
                saved["runs"].setdefault(label, {})[name] = in_child(scenario, name, code=code)
    write_text_atomic(RESULTS, json.dumps(saved, indent=2, default=str))
    _write(saved)
    return 0


def _write(saved: dict) -> None:
    """The Markdown section (``rgbd_memory.md`` beside the JSON), also printed."""
    text = "\n".join([
        "## RGB-D memory and throughput (issue 25, item 3)", "",
        f"- Command: `{saved['command']}`", f"- Machine: {saved['machine']}",
        "- Each run in its own process; peak RSS includes the final optimisation and mesh. The "
        "breakdown tables give the sample with the highest RSS, the last frame's and the end's.",
        "", table(saved)])  # fmt: skip
    write_text_atomic(RESULTS.with_suffix(".md"), text.rstrip() + "\n")
    print(text)


if __name__ == "__main__":
    sys.exit(main())
