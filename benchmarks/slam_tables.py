"""Markdown tables of ``bench_slam`` (and ``bench_vertical``) results."""

from __future__ import annotations

import numpy as np


def fmt(value, unit: str = "", digits: int = 3) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}f}{unit}"
    return f"{value}{unit}"


def cm(value) -> str:
    return "n/a" if value is None else f"{100 * value:.2f}"


def false_loops(r: dict, false_m: float, false_deg: float) -> tuple[int, int]:
    """Verified loops (and those the graph kept) whose pose is off by more than the limits."""
    wrong = [m > false_m or d > false_deg for m, d in r["loop_errors"]]
    return sum(wrong), sum(w and k for w, k in zip(wrong, r["loop_kept"], strict=True))


def trajectory_table(rows: list[tuple[str, dict, tuple[float, float]]]) -> list[str]:
    lines = [
        "| run | frames | submaps | loop candidates | verified | kept by graph | false verified "
        "/ kept (limit) | median loop error [cm / deg] | ATE odometry [m] | ATE SLAM [m] | "
        "ATE x / y / z odometry -> SLAM [m] | frames/s | peak RSS [MB] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def axes(r: dict) -> str:
        if "ate_xyz_slam_m" not in r:  # results saved before the per-axis split
            return "n/a"
        odometry, slam = (
            " / ".join(f"{v:.3f}" for v in r[k]) for k in ("ate_xyz_odometry_m", "ate_xyz_slam_m")
        )
        return f"{odometry} -> {slam}"

    for name, r, (false_m, false_deg) in rows:
        wrong, wrong_kept = false_loops(r, false_m, false_deg)
        errors = np.array(r["loop_errors"]).reshape(-1, 2)
        median = (
            f"{100 * np.median(errors[:, 0]):.1f} / {np.median(errors[:, 1]):.2f}"
            if len(errors)
            else "n/a"
        )
        lines.append(
            f"| {name} | {r['frames']} | {r['submaps']} | {r['candidates']} | {r['verified']} | "
            f"{r['kept']} | {wrong} / {wrong_kept} ({100 * false_m:.0f} cm, {false_deg:.0f} deg) | "
            f"{median} | {r['ate_odometry_m']:.3f} | {r['ate_slam_m']:.3f} | {axes(r)} | "
            f"{r['fps']:.2f} | "
            f"{r['peak_rss_mb']:.0f} |"
        )
    return lines


def remap_table(rows: list[tuple[str, dict]]) -> list[str]:
    lines = [
        "| run | remap passes | submap moves | frames moved | total [s] | max per pass [s] | "
        "submaps/s | frames/s (paper: 50) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows:
        seconds = r["remap_s_total"]
        sub_rate = r["remap_moved"] / seconds if seconds > 0 else None
        frame_rate = r["remap_frames_moved"] / seconds if seconds > 0 else None
        lines.append(
            f"| {name} | {r['remap_events']} | {r['remap_moved']} | {r['remap_frames_moved']} | "
            f"{seconds:.2f} | {r['remap_s_max']:.2f} | {fmt(sub_rate, digits=1)} | "
            f"{fmt(frame_rate, digits=1)} |"
        )
    return lines


def stage_table(rows: list[tuple[str, dict]]) -> list[str]:
    stages = ["odometry", "keyframing", "mapping", "loop_detection", "pose_graph", "remap"]
    lines = [
        "| run | " + " | ".join(stages) + " | whole run |",
        "|---|" + "---|" * (len(stages) + 1),
    ]
    for name, r in rows:
        cells = [fmt(r["stage_s"].get(s, 0.0), digits=1) for s in stages]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {r['wall_s']:.1f} |")
    return lines
