"""LiDAR throughput: KISS-ICP alone, KISS-SLAM and ours on the same generated KITTI-00 scans.

    python -m benchmarks.bench_throughput [--frames N] [--before REV] [--skip-kiss-slam] [--quick]
    python -m benchmarks.bench_throughput --only ours --frames 1000 --profile
    python -m benchmarks.bench_throughput --report-only

The scans are benchmarks.harness.kitti's (the full window; ``--quick``: the first 100 scans of the
quick window, no KISS-SLAM; ``--frames N``: the first N). Every method runs ``REPEATS`` times in
its own process, so its peak memory is its own. Ours runs as ``slam.run --no-viz`` does
(configs/kitti.yaml, final optimisation, mesh and ``map.npz``), its RSS sampled every 1,000 frames
with a per-object breakdown (:mod:`benchmarks.memory_breakdown`). ``--before REV`` also measures
ours at REV, checked out beside this tree. ``--profile`` runs ours under cProfile with the
workers inline and writes ``benchmarks/results/throughput_profile.md``.
Writes ``benchmarks/results/throughput.json`` and ``throughput.md``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchmarks.harness.checkout import revisions
from benchmarks.harness.child import UnsupportedRevision, in_child
from benchmarks.harness.cli import bench_parser, command_line, start_logging
from benchmarks.harness.kitti import KITTI_POSES, have_kitti, kitti_source, window
from benchmarks.harness.machine import machine_line, proc_memory_kib
from benchmarks.harness.paths import RESULTS_DIR
from benchmarks.harness.pipeline import QUIET
from benchmarks.harness.reference import kiss_icp_alone, kiss_slam
from benchmarks.harness.repeat import REPEATS, repeat_runs, restore_all
from benchmarks.memory_breakdown import memory_breakdown, trim_mb
from benchmarks.throughput_report import RSS_EVERY, write_report
from common.atomic_io import write_text_atomic
from mapping.map_io import save_map
from slam.assembly.threads import machine_cores

METHODS = ("ours", "kiss_icp", "kiss_slam")
QUICK_FRAMES = 100
RESULTS = RESULTS_DIR / "throughput.json"
TIMING_KEYS = ("wall_s", "cpu_s", "fps", "stage_s", "stage_cpu_s", "cpu_threads_s")
"""What :func:`_measure` repeats (every method that has them); the rest is the first run's."""

log = logging.getLogger("benchmarks.bench_throughput")


def _rss_mb() -> tuple[float, float]:
    """(current, peak) resident memory of this process in MB (MiB, as before)."""
    memory = proc_memory_kib()
    return memory.get("VmRSS", float("nan")) / 1024, memory.get("VmHWM", float("nan")) / 1024


def _phase_peak() -> float:
    """Peak RSS (MB) since the last call, then the peak counter reset (``clear_refs``; where
    that is refused the peak stays cumulative, which only makes later phases read high)."""
    peak = _rss_mb()[1]
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")
    return peak


def _breakdown(pipeline, baseline_mb: float) -> dict[str, float]:
    """The per-object memory breakdown, with what trimming the heap returned."""
    out = memory_breakdown(pipeline, baseline_mb)
    returned = trim_mb()
    out["trim_returned"] = float("nan") if returned is None else returned
    return out


def _child_usage(odometry) -> Callable[[], Any] | None:
    """How to read the CPU time and memory of the odometry's child process where it runs in one
    (``odometry.child_process``), else None: the run's figures must include it."""
    from frontends.odometry.child_process import ChildProcessOdometry

    return odometry.usage if isinstance(odometry, ChildProcessOdometry) else None


def _profile_summary(profile, top: int = 30) -> str:
    """The top functions of a cProfile run by cumulative and by own time."""
    import io
    import pstats

    out = []
    for key in ("cumulative", "tottime"):
        text = io.StringIO()
        pstats.Stats(profile, stream=text).strip_dirs().sort_stats(key).print_stats(top)
        body = text.getvalue()
        out.append(f"### by {key} time\n\n```\n{body[body.index('ncalls') :].rstrip()}\n```")
    return "\n\n".join(out)


def _config(extra: dict[str, Any] | None = None):
    """configs/kitti.yaml for the generated scans, without viewer, with ``extra`` on top."""
    from slam.assembly.config import default_config_path, load_run_config, merge_overrides

    overrides = merge_overrides({"source": {"dataset": "generated"}, **QUIET}, extra or {})
    return load_run_config(default_config_path("kitti"), overrides)


def _apply_thread_budget(cfg) -> str:
    """Apply the run's thread budget, as ``slam.run`` does; its description."""
    from slam.assembly.threads import apply_thread_budget

    return apply_thread_budget(cfg).describe()


def scenario_ours(
    quick: bool,
    num_frames: int,
    override: dict[str, Any] | None = None,
    relief_m: float = 0.0,
    profile: bool = False,
) -> dict:
    logging.basicConfig(level=logging.WARNING)
    from slam.algorithm.pipeline import SlamPipeline
    from slam.assembly.builders import build_map, build_odometry
    from slam.evaluation.metrics.trajectory import ate_per_axis_rmse, ate_rmse

    cfg = _config(override)
    threads = _apply_thread_budget(cfg)
    if profile:  # every stage on the profiled thread, with the threaded run's thread budget
        cfg.map_worker = False
    source = kitti_source(quick, num_frames, relief_m)
    odometry = build_odometry(cfg, "lidar")
    neural_map = build_map(cfg)
    pipeline = SlamPipeline(cfg.pipeline_config(), "lidar", odometry, neural_map)
    rss: dict[str, float] = {}
    memory: dict[str, dict[str, float] | None] = {}
    baseline_mb = _rss_mb()[0] * 1024**2 / 1e6
    profiler = None
    if profile:
        import cProfile

        profiler = cProfile.Profile(time.process_time)  # CPU: steadier than wall under load
        profiler.enable()
    start = time.perf_counter()
    cpu_start = time.process_time()
    main_cpu_start = time.thread_time()
    child_usage = _child_usage(odometry)
    count = 0
    instrument_s = 0.0  # the memory breakdowns' own time, left out of the wall time
    for frame in source.read_ahead():
        pipeline.process(frame)
        count += 1
        if count % RSS_EVERY == 0:
            mark = time.perf_counter()
            child_rss_mb = child_usage().rss_mb if child_usage else 0.0
            rss[str(count)] = _rss_mb()[0] + child_rss_mb
            memory[str(count)] = _breakdown(pipeline, baseline_mb)
            if child_usage and memory[str(count)] is not None:
                memory[str(count)]["odometry_process_rss"] = child_rss_mb
            instrument_s += time.perf_counter() - mark
    child = child_usage() if child_usage else None  # its work is done: finish() ends it
    phase_peaks = {"frames": _phase_peak() + (child.peak_rss_mb if child else 0.0)}
    pipeline.finish()
    main_cpu_s = time.thread_time() - main_cpu_start
    phase_peaks["finish"] = _phase_peak()
    mark = time.perf_counter()
    memory["finished"] = _breakdown(pipeline, baseline_mb)
    instrument_s += time.perf_counter() - mark
    mark = time.perf_counter()
    from slam.assembly.threads import plan_thread_budget

    mesh_threads = plan_thread_budget(cfg.threads, cfg.map_worker).mesh_threads
    mesh = neural_map.extract_mesh(threads=mesh_threads)
    final_mesh_s = time.perf_counter() - mark
    phase_peaks["final_mesh"] = _phase_peak()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "map.npz"
        save_map(neural_map, path, list(pipeline.submaps.values()))
        map_bytes = path.stat().st_size
    phase_peaks["map_save"] = _phase_peak()
    wall = time.perf_counter() - start - instrument_s
    cpu_s = time.process_time() - cpu_start + (child.cpu_s if child else 0.0)
    if profiler is not None:
        profiler.disable()
    map_save_s = wall - final_mesh_s - (mark - start - instrument_s)
    rss[str(count)] = _rss_mb()[0]
    peak_rss_mb = max(phase_peaks.values())  # before scoring: the run's own peak
    gt = source.gt_poses
    from slam.evaluation.metrics.trajectory import align_se3
    from slam.evaluation.run_metrics import mesh_errors

    errors = mesh_errors(
        mesh,
        source.gt_mesh_path,
        align_se3(pipeline.slam_poses(), gt),
        50_000,
        gt,
        lidar_range_m=cfg.submaps.max_range_m,
    )
    stage = {k: float(sum(v)) for k, v in pipeline.timings_s.items() if k != "frame"}
    stage.update(final_mesh=final_mesh_s, map_save=map_save_s)
    workers = pipeline.executor
    odometry_poses, slam_poses = pipeline.frames.odometry_poses(), pipeline.slam_poses()
    return {
        "frames": count,
        "wall_s": wall,
        "cpu_s": cpu_s,
        # main thread up to the end of finish(); the map worker's thread; the rest is KISS-ICP's
        # thread pool, reading ahead, the final mesh and the map file
        "cpu_threads_s": {
            "main": main_cpu_s,
            "map_worker": workers.map_worker.cpu_s,
            "submap_worker": workers.submap_worker.cpu_s,
            "odometry_process": child.cpu_s if child else None,
        },
        "odometry_process_peak_rss_mb": child.peak_rss_mb if child else None,
        "fps": count / wall,
        "stage_s": stage,
        "stage_cpu_s": dict(pipeline.stage_cpu_s),
        "rss_mb": rss,
        "memory_mb": memory,
        "phase_peak_rss_mb": phase_peaks,
        "peak_rss_mb": peak_rss_mb,
        "peak_rss_with_scoring_mb": _rss_mb()[1],
        "map_npz_mb": map_bytes / 1e6,
        "map_voxels": neural_map.num_voxels,
        "submaps": len(pipeline.submaps),
        "loops_kept": sum(1 for c in pipeline.accepted_loops() if c.graph_inlier),
        "ate_odometry_m": ate_rmse(odometry_poses, gt),
        "ate_slam_m": ate_rmse(slam_poses, gt),
        "ate_xyz_odometry_m": ate_per_axis_rmse(odometry_poses, gt).tolist(),
        "ate_xyz_slam_m": ate_per_axis_rmse(slam_poses, gt).tolist(),
        "mesh_accuracy_m": errors["accuracy_m"],
        "mesh_faces": len(mesh.faces),
        "threads": threads,
        "workers": "inline (profiled)" if profile else "threaded",
        **({"profile": _profile_summary(profiler)} if profiler is not None else {}),
    }


def scenario_kiss_icp(quick: bool, num_frames: int, relief_m: float = 0.0) -> dict:
    logging.basicConfig(level=logging.WARNING)
    cfg = _config()
    threads = _apply_thread_budget(cfg)
    out = kiss_icp_alone(kitti_source(quick, num_frames, relief_m), cfg.odometry.kiss_icp.to_kiss())
    return {**out, "peak_rss_mb": _rss_mb()[1], "threads": threads}


def build_parser():
    quick = f"the first {QUICK_FRAMES} scans of the quick window, no KISS-SLAM"
    parser = bench_parser(__doc__, quick, before=True)
    parser.add_argument("--frames", type=int, help="first N scans (default: the whole window)")
    parser.add_argument("--only", choices=METHODS, action="append")
    parser.add_argument("--skip-kiss-slam", action="store_true")
    parser.add_argument(
        "--override",
        type=json.loads,
        default=None,
        help="config overrides for ours, as JSON; recorded",
    )
    parser.add_argument(
        "--relief",
        type=float,
        default=0.0,
        help="generated.terrain_relief_m: hills beside the road",
    )
    parser.add_argument("--profile", action="store_true", help="ours under cProfile, inline")
    parser.add_argument("--report-only", action="store_true", help="rewrite from the .json")
    return parser


def _measure(name: str, args, code: Path | None) -> dict:
    """One method in its own process; ``code``: the checkout whose ``slam`` it imports."""
    if name == "kiss_slam":
        run = (args.quick, args.frames, args.relief)
        return repeat_runs(lambda: kiss_slam(kitti_source(*run), args.frames), TIMING_KEYS)
    fn, fn_args = scenario_kiss_icp, (args.quick, args.frames, args.relief)
    if name == "ours":
        fn, fn_args = scenario_ours, (*fn_args[:2], args.override, args.relief, args.profile)
    repeats = 1 if args.profile else REPEATS
    try:
        return repeat_runs(lambda: in_child(fn, *fn_args, code=code), TIMING_KEYS, repeats)
    except UnsupportedRevision as error:
        return {"skipped": str(error)}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.report_only:
        write_report(restore_all(json.loads(RESULTS.read_text())))
        return 0
    if not have_kitti():
        log.error("no %s: the throughput benchmark needs KITTI 00's poses", KITTI_POSES)
        return 1
    w = window(args.quick)
    args.frames = min(args.frames or w.num_frames, QUICK_FRAMES if args.quick else w.num_frames)
    start_logging("%(asctime)s %(name)s: %(message)s")
    saved: dict[str, Any] = {
        "command": command_line("bench_throughput", argv),
        "machine": machine_line(),
        "quick": args.quick,
        "frames": args.frames,
        "relief": args.relief,
        "override": args.override,
        "cores": machine_cores(),
        "runs": {},
    }
    methods = list(args.only or ["kiss_icp", "kiss_slam", "ours"])
    if (args.skip_kiss_slam or args.quick) and "kiss_slam" in methods:
        methods.remove("kiss_slam")
    with revisions(args.before) as codes:
        for label, code in codes.items():
            run = saved["runs"].setdefault(label, {"code": label})
            for name in methods:
                if code is not None and name in ("kiss_icp", "kiss_slam"):
                    continue  # reference systems: independent of our code
                log.info("%s (%s), %d frames", name, label, args.frames)
                run["load"] = os.getloadavg()[0]
                run[name] = _measure(name, args, code)
    write_text_atomic(RESULTS, json.dumps(saved, indent=2, default=str))
    write_report(saved)
    return 0


if __name__ == "__main__":
    sys.exit(main())
