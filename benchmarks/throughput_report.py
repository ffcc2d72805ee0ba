"""The Markdown section of ``bench_throughput`` (``benchmarks/results/throughput.md``)."""

from __future__ import annotations

import numpy as np

from benchmarks.harness.kitti import window
from benchmarks.harness.paths import RESULTS_DIR
from benchmarks.harness.results import table
from common.atomic_io import write_text_atomic

REPORT = RESULTS_DIR / "throughput.md"
PROFILE_REPORT = RESULTS_DIR / "throughput_profile.md"
RSS_EVERY = 1000
STAGES = (
    "odometry",
    "submap_worker_wait",
    "keyframing",
    "mapping",
    "loop_detection",
    "pose_graph",
    "remap",
    "map_logging",
    "final_mesh",
    "map_save",
)


def _f(value, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}f}"


def write_report(saved: dict) -> None:
    results = saved["runs"]
    lines = [
        "## LiDAR throughput",
        "",
        f"- Command: `{saved['command']}`",
        f"- Machine: {saved['machine']}",
        f"- Sequence: generated scans along {window(saved['quick']).describe(saved['frames'])}"
        + (f", {saved['relief']:g} m hills" if saved["relief"] else ""),
        "- Runs: `after` is this checkout; `before <rev>` (with `--before`) is that revision "
        "checked out beside it and measured in the same invocation. KISS-ICP and KISS-SLAM do "
        "not depend on our code and run once.",
        "",
        "Generated 64-beam LiDAR along the real KITTI 00 trajectory (2048 firings per revolution, "
        "~128k points per scan), configs/kitti.yaml, `NullLogger` (as `--no-viz`), CPU only, "
        "2 cores shared with other jobs (the load average is part of each row). Ours includes "
        "reading the scans, the final optimisation, the final mesh and writing `map.npz`; "
        "KISS-ICP alone is reading + `register_frame`; KISS-SLAM is its `kiss_slam_pipeline` "
        "process (0.0.2, default config). Ours' peak RSS is taken before its mesh is scored "
        "against ground truth (evaluation, not SLAM; `peak_rss_with_scoring_mb` in "
        "throughput.json). CPU = user + system time of all the method's threads (where "
        "recorded): on two cores that are both busy, the wall time is about half of it, and it "
        "varies less between runs than the wall time.",
        "",
    ]
    rows, skipped = [], []
    for key in sorted(results):
        run = results[key]
        icp, kslam = run.get("kiss_icp") or {}, run.get("kiss_slam") or {}
        for name in ("kiss_icp", "kiss_slam", "ours"):
            r = run.get(name)
            if r and "skipped" in r:
                skipped.append(f"- {key}, {name}: skipped ({r['skipped']})")
            if not r or "skipped" in r or "frames" not in r:
                continue
            vs_icp = r["wall_s"] / icp["wall_s"] if icp.get("wall_s") else None
            vs_slam = r["wall_s"] / kslam["wall_s"] if kslam.get("wall_s") else None
            rows.append(
                [
                    key,
                    run["code"],
                    r["frames"],
                    name,
                    _f(r["wall_s"]),
                    _f(r.get("cpu_s"), 0),
                    _f(r["fps"], 2),
                    _f(vs_icp, 2),
                    _f(vs_slam, 2),
                    _f(r.get("peak_rss_mb"), 0),
                    _f(r.get("ate_odometry_m"), 3),
                    _f(r.get("ate_slam_m"), 3),
                    _f(run.get("load"), 1),
                ]
            )
    header = (
        "run | code | frames | method | wall [s] | CPU [s] | frames/s | vs KISS-ICP | "
        "vs KISS-SLAM | peak RSS [MB] | ATE odometry [m] | ATE SLAM [m] | load"
    )
    lines += table(header, rows)
    lines += ["", *skipped] if skipped else []
    lines += _cpu_floor_lines(saved)
    lines += _per_axis_lines(results)
    lines += [
        "",
        "Ours, per stage [s] (`map_logging` is the null logger's share; with the map worker, "
        "mapping and remap run on a second thread, overlapped with odometry, so the stages can "
        "add up to more than the whole run; CPU: the main thread's CPU time to the end of the "
        "final remap, the submap worker thread's (0 where it has none), the map worker "
        "thread's (0 with the workers inline), the odometry's child process (KISS-ICP and its "
        "thread pool, with `odometry.child_process`; 0 without), and the rest (KISS-ICP's "
        "thread pool when it runs in the process, reading ahead, the final mesh, writing the "
        "map); RSS: the process's and the odometry process's together; `final_mesh` is the "
        "whole map meshed after the last remap (on the whole thread budget) and `map_save` writing "
        "`map.npz`, both after the last frame; n/a: not timed then), memory and map:",
        "",
    ]
    rows = []
    for key in sorted(results):
        r = results[key].get("ours")
        if not r or "skipped" in r:
            continue
        rss = ", ".join(f"{k}: {v:.0f}" for k, v in r["rss_mb"].items())
        threads, cpu = r.get("cpu_threads_s"), "n/a"
        if threads:
            parts = [
                threads["main"],
                threads.get("submap_worker") or 0.0,
                threads["map_worker"] or 0.0,
                threads.get("odometry_process") or 0.0,
            ]
            cpu = " / ".join(f"{v:.0f}" for v in (*parts, r["cpu_s"] - sum(parts)))
        rows.append(
            [
                key,
                *(_f(r["stage_s"].get(s)) for s in STAGES),
                _f(r["wall_s"]),
                cpu,
                rss,
                f"{r['map_npz_mb']:.1f}",
                f"{r['map_voxels']:,}",
                f"{100 * r['mesh_accuracy_m']:.2f}",
                r["threads"],
            ]
        )
    lines += table(
        "run | " + " | ".join(STAGES) + " | whole run | CPU main / submap worker / map "
        f"worker / odometry process / other [s] | RSS at {RSS_EVERY:,}-frame steps [MB] "
        "| map.npz [MB] | voxels | mesh accuracy [cm] | threads",
        rows,
    )
    shares = [k for k in sorted(results) if (results[k].get("ours") or {}).get("stage_cpu_s")]
    if shares:
        lines += [
            "",
            "Ours, the stages' shares of the run: CPU seconds of the thread that ran each stage "
            "(the map worker's for mapping and remap; KISS-ICP's own thread pool is not in "
            "odometry's), as a share of the run's wall time and of its CPU time. A stage on the "
            "map worker overlaps the main thread, so its wall time there is mostly waiting for "
            "a core; `map_worker_wait` is what the main thread lost waiting for the worker.",
            "",
        ]
        rows = []
        for key in shares:
            r = results[key]["ours"]
            cpu = r["stage_cpu_s"]
            rows += [
                [
                    key,
                    stage,
                    _f(r["stage_s"].get(stage)),
                    f"{cpu[stage]:.1f}",
                    f"{100 * cpu[stage] / r['wall_s']:.0f} %",
                    f"{100 * cpu[stage] / r['cpu_s']:.0f} %",
                ]
                for stage in (*STAGES, "map_worker_wait")
                if stage in cpu
            ]
        lines += table("run | stage | wall [s] | CPU [s] | CPU / run wall | CPU / run CPU", rows)
    lines += _memory_lines(results)
    lines.append("")
    write_text_atomic(REPORT, "\n".join(lines))
    _write_profiles(saved)


MEMORY_PARTS = (
    ("baseline", "baseline (code, torch, libraries; before the first frame)"),
    ("kiss_icp_local_map", "KISS-ICP local map (24 B a point)"),
    ("loop_clouds", "loop clouds kept for verification"),
    ("place_descriptors", "place descriptors"),
    ("submap_records", "submap records (points until encoded)"),
    ("keyframer_buffers", "keyframer buffers (open submap)"),
    ("neural_map_submaps", "neural map: submap originals (for remapping)"),
    ("neural_map_store_and_mesh", "neural map: voxel store and mesh cache"),
    ("per_frame_poses", "per-frame poses"),
    ("pose_graph_and_remap_events", "pose graph and remap events (arrays)"),
    ("unattributed", "unattributed (resident slack, Python objects, C++ containers)"),
    ("allocator_free", "glibc free chunks (resident or not; in the line above where resident)"),
    ("rss", "RSS"),
    ("trim_returned", "of which malloc_trim(0) returned right after"),
    ("odometry_process_rss", "odometry child process (KISS-ICP, its local map): its own RSS"),
)


def _cpu_floor_lines(saved: dict) -> list[str]:
    """Ours' CPU time over the machine's cores: the wall time no schedule of the same work can
    beat, set against KISS-SLAM's wall."""
    cores = saved.get("cores")
    if not cores:
        return []
    lines = []
    for key in sorted(saved["runs"]):
        run = saved["runs"][key]
        ours = run.get("ours") or {}
        kslam = run.get("kiss_slam") or saved["runs"].get("after", {}).get("kiss_slam") or {}
        if not ours.get("cpu_s") or not kslam.get("wall_s"):
            continue
        floor = ours["cpu_s"] / cores
        lines.append(
            f"- {key}: ours' CPU over the {cores} cores is {floor:.0f} s, "
            f"{floor / kslam['wall_s']:.2f}x KISS-SLAM's wall; its wall is "
            f"{ours['wall_s'] / floor:.2f}x that floor. Ours reaches KISS-SLAM's wall only "
            f"with at most {cores * kslam['wall_s']:.0f} CPU-s, however its threads are "
            "scheduled."
        )
    if not lines:
        return []
    return ["", "Lower bound of ours' wall time: its CPU time divided by the cores.", "", *lines]


def _memory_lines(results: dict) -> list[str]:
    """Ours' per-object memory breakdown at each sample (``memory_mb``), where recorded."""
    lines = []
    for key in sorted(results):
        memory = (results[key].get("ours") or {}).get("memory_mb") or {}
        samples = [(k, v) for k, v in memory.items() if v]
        if not samples:
            continue
        numbered = [(k, v) for k, v in samples if k.isdigit()]
        growth = ""
        if len(numbered) >= 2:
            (k0, first), (k1, last) = numbered[0], numbered[-1]
            per = (last["rss"] - first["rss"]) / ((int(k1) - int(k0)) / RSS_EVERY)
            growth = f" RSS growth {per:.0f} MB per {RSS_EVERY:,} frames ({k0} to {k1})."
        phases = (results[key].get("ours") or {}).get("phase_peak_rss_mb") or {}
        if phases:
            peaks = ", ".join(f"{k} {v:.0f}" for k, v in phases.items())
            growth += f" Peak RSS [MiB] by phase: {peaks}."
        lines += [
            "",
            f"Ours ({key}), memory by object [MB, 10^6 bytes] at frame N and after `finish()`"
            f" (benchmarks/memory_breakdown.py).{growth}",
            "",
            *table(
                "part | " + " | ".join(k for k, _ in samples),
                (
                    [label, *(_f(v.get(part), 1) for _, v in samples)]
                    for part, label in MEMORY_PARTS
                ),
            ),
        ]
    return lines


def _write_profiles(saved: dict) -> None:
    """``throughput_profile.md`` from the runs made with ``--profile`` (left alone otherwise)."""
    sections = []
    for key in sorted(saved["runs"]):
        r = saved["runs"][key].get("ours") or {}
        if r.get("profile"):
            sections.append(
                f"## {key}: {r['frames']} scans, wall {r['wall_s']:.1f} s, CPU {r['cpu_s']:.1f} s "
                f"under cProfile (workers inline), load {_f(saved['runs'][key].get('load'), 1)}\n\n"
                + r["profile"]
            )
    if not sections:
        return
    head = (
        "# LiDAR profile (bench_throughput --profile)\n\n"
        f"- Command: `{saved['command']}`\n- Machine: {saved['machine']}\n\n"
        "cProfile of ours with the submap and map workers inline, so every stage runs on the "
        "profiled thread, with the threaded run's thread budget (torch on one thread); times "
        "are CPU seconds of the whole process (`time.process_time`: KISS-ICP's thread pool and "
        "the read-ahead thread count towards the function running meanwhile), steadier than "
        "wall time on a shared machine. Native code, e.g. KISS-ICP's registration, counts as the "
        "own time of the Python function that called it.\n\n"
    )
    write_text_atomic(PROFILE_REPORT, head + "\n\n".join(sections) + "\n")


def _per_axis_lines(results: dict) -> list[str]:
    """Per-axis ATE (RMSE along world x, y, z after the SE(3) alignment) where recorded."""
    rows = []
    for key in sorted(results):
        for name in ("kiss_icp", "kiss_slam", "ours"):
            r = results[key].get(name) or {}
            odometry, slam = r.get("ate_xyz_odometry_m"), r.get("ate_xyz_slam_m")
            if odometry is None and slam is None:
                continue
            cells = [
                "n/a" if xyz is None else " / ".join(f"{v:.3f}" for v in xyz)
                for xyz in (odometry, slam)
            ]
            rows.append([key, name, *cells])
    if not rows:
        return []
    header = "run | method | odometry x / y / z | SLAM x / y / z"
    return ["", "Per-axis ATE [m] (x / y / z, z up), where recorded:", "", *table(header, rows)]
