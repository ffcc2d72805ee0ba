"""The CSV of a sweep: one row per combination of the grid, read from each run's
``metrics.json`` (SLAM ATE in all and per axis where the recording has ground truth, loops, map
size (voxels and the bytes of ``map.npz``), wall time, peak RSS)."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

METRIC_COLUMNS = (
    "state",
    "ate_rmse_m",
    "ate_x_rmse_m",
    "ate_y_rmse_m",
    "ate_z_rmse_m",
    "loops_kept",
    "loops_verified",
    "submaps",
    "map_voxels",
    "map_npz_bytes",
    "wall_s",
    "frames_per_s",
    "peak_rss_mb",
)


def metric_row(folder: Path, finished: bool) -> dict[str, Any]:
    """The metric columns of one run folder (empty where the run has no such figure)."""
    path = folder / "metrics.json"
    if not finished or not path.is_file():
        return {"state": "failed"}
    metrics = json.loads(path.read_text())
    slam = (metrics.get("trajectory") or {}).get("slam") or {}
    loops = metrics.get("loops") or {}
    size = metrics.get("map") or {}
    timing = metrics.get("timing") or {}
    map_file = folder / "map.npz"
    return {
        "state": "finished",
        **{key: slam.get(key) for key in METRIC_COLUMNS[1:5]},
        "loops_kept": loops.get("graph_inliers"),
        "loops_verified": loops.get("verified"),
        "submaps": metrics.get("num_submaps"),
        "map_voxels": size.get("voxels"),
        "map_npz_bytes": map_file.stat().st_size if map_file.is_file() else None,
        "wall_s": timing.get("wall_s"),
        "frames_per_s": timing.get("frames_per_s"),
        "peak_rss_mb": (metrics.get("memory") or {}).get("peak_rss_mb"),
    }


def sweep_csv(rows: list[tuple[str, dict[str, Any], dict[str, Any]]], keys: list[str]) -> str:
    """``rows``: (run name, grid values, :func:`metric_row`) per combination."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(("run", *keys, *METRIC_COLUMNS))
    for name, values, metrics in rows:
        writer.writerow(
            (name, *(values[key] for key in keys), *(_cell(metrics.get(c)) for c in METRIC_COLUMNS))
        )
    return buffer.getvalue()


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)
