"""The short summary printed at the end of a run."""

from __future__ import annotations

from typing import Any

import numpy as np


def _length(value: float | None) -> str:
    if value is None or not np.isfinite(value):
        return "n/a"
    return f"{value * 100:.1f} cm" if value < 1.0 else f"{value:.2f} m"


_UNCULLED = {
    "frustum": "all ground truth in a camera's view, occluded surfaces too",
    "none": "the whole ground truth",
}


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
    trajectory = metrics.get("trajectory")
    if trajectory:
        lines.append(
            f"ATE odometry {_length(trajectory['odometry']['ate_rmse_m'])} -> "
            f"SLAM {_length(trajectory['slam']['ate_rmse_m'])}"
        )
    mesh = metrics.get("mesh")
    if mesh:
        culling = str(mesh.get("culling", ""))
        where = (
            "over observed surfaces"
            if culling.startswith("observed")
            else {"frustum": "over surfaces in view", "none": "over the whole ground truth"}.get(
                culling, f"culling {culling}"
            )
        )
        lines.append(
            f"mesh accuracy {_length(mesh['accuracy_m'])}, completion "
            f"{_length(mesh['completion_m'])}, completion ratio "
            f"{100 * mesh['completion_ratio']:.0f}% (< {_length(mesh['threshold_m'])}) {where}"
        )
        unculled = metrics.get("mesh_unculled")
        if unculled:
            lines.append(
                f"  unculled ({_UNCULLED.get(unculled.get('culling'), unculled.get('culling'))}): "
                f"completion {_length(unculled['completion_m'])}, ratio "
                f"{100 * unculled['completion_ratio']:.0f}%"
            )
    for warning in metrics.get("warnings", []):
        lines.append(f"WARNING: {warning}")
    if metrics.get("recording"):
        lines.append(f"replay: rerun {metrics['recording']}")
    return lines
