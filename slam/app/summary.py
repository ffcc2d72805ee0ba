"""The short summary printed at the end of a run."""

from __future__ import annotations

from typing import Any

from slam.evaluation.summary import length, mesh_lines


def summary_lines(metrics: dict[str, Any]) -> list[str]:
    """The short summary printed at the end of a run."""
    timing = metrics["timing"]
    loops = metrics["loops"]
    remap = metrics["remap"]
    rate = timing.get("frames_per_s")
    lines = [
        f"run folder: {metrics['run_folder']}",
        f"frames {metrics['num_frames']}: pipeline {rate or 0.0:.1f} frames/s "
        f"({timing.get('pipeline_s', timing['wall_s']):.1f} s); wall time {timing['wall_s']:.1f} s "
        "(with loading/generating data, final mesh and files)",
        f"submaps {metrics['num_submaps']}; "
        f"loops {loops['graph_inliers']} kept / {loops['verified']} verified / "
        f"{loops['candidates']} candidates",
        f"remapping: {remap['submaps_moved']} submap moves in {remap['events']} passes, "
        f"{remap['seconds_total']:.2f} s; map {metrics['map']['voxels']} voxels",
    ]
    if "localisation" in metrics and not metrics["map"]["voxels"]:
        lines[-1] = "localisation only: no map kept (no submap encoded)"
    placed = metrics.get("relocalisation")
    if placed is not None:
        lines.append(
            f"relocalised in the map by frames {placed['submap_frames'][0]}-"
            f"{placed['submap_frames'][1]} ({placed['submaps_tried']} submaps tried, "
            f"{placed['seconds']:.1f} s)"
            if placed["relocalised"]
            else f"not relocalised in the map ({placed['submaps_tried']} submaps tried)"
        )
    anchored = metrics.get("localisation")
    if anchored is not None and placed is not None and placed["relocalised"]:
        gaps = ", ".join(f"{a}-{b}" for a, b in anchored["coverage_gaps"][:5]) or "none"
        lines.append(
            f"map-anchored frames {100 * anchored['fraction_anchored']:.0f} % "
            f"({anchored['frames_before_placement']} before the placement); odometry-only "
            f"stretches after it: {gaps}"
        )
    trajectory = metrics.get("trajectory")
    if trajectory:
        lines.append(
            f"ATE odometry {length(trajectory['odometry']['ate_rmse_m'])} -> "
            f"SLAM {length(trajectory['slam']['ate_rmse_m'])}"
        )
        slam = trajectory["slam"]
        lines.append(
            f"SLAM relative to its first pose, unaligned: "
            f"{length(slam['unaligned_rmse_m'])}, yaw {slam['unaligned_yaw_mean_abs_deg']:.2f} "
            f"deg, tilt {slam['unaligned_tilt_mean_deg']:.2f} deg (means)"
        )
    lines += mesh_lines(metrics)
    for warning in metrics.get("warnings", []):
        lines.append(f"WARNING: {warning}")
    if metrics.get("recording"):
        lines.append(f"replay: rerun {metrics['recording']}")
    return lines
