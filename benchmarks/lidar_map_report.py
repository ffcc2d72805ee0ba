"""The Markdown section of ``benchmarks.bench_lidar_map``: quality and cost tables, targets."""

from __future__ import annotations

from typing import Any

from benchmarks.harness.lidar_surface import (
    OBSERVED_DISTANCE_M,
    OBSERVED_POINT_VOXEL_M,
    POINT_THRESHOLDS_M,
    THRESHOLDS_M,
)
from benchmarks.harness.results import cm, table

KIND_TITLES = {
    "gt": "Generated street, ground-truth poses (`odometry.method: gt`)",
    "kiss-icp": "Generated street, SLAM poses (KISS-ICP, loop closure, remapping)",
    "mulran": "MulRan Riverside02 keyframes, reference poses (precision against the scan points)",
}
TARGET_RSS_WALL_RATIO = 1.3
TARGET_PRECISION = 0.9
TARGET_FILE_SHARE = 0.1


BEFORE_ROWS = "neural map, before"
"""The rows of the 'before' configuration: shown over all scans only (per stretch, the sharpness
in question is today's map's; the .json keeps every stretch)."""


def _quality_table(by_name: dict[str, dict], points_only: bool) -> list[str]:
    metrics = [(f"precision_{t:g}", f"P@{100 * t:g}") for t in POINT_THRESHOLDS_M]
    if not points_only:
        metrics = [
            (f"{kind}_{t:g}", f"{label}@{100 * t:g}")
            for t in THRESHOLDS_M
            for kind, label in (("precision", "P"), ("recall", "R"), ("f", "F"))
        ]
    distances = ["accuracy"] + ([] if points_only else ["completion"])
    header = [
        "map",
        "region",
        "observed within",
        *(label for _, label in metrics),
        *(f"{d} [cm]" for d in distances),
    ]
    rows = [
        [
            name,
            row["region"],
            f"{row['range_m']:g} m",
            *(f"{row[key]:.3f}" for key, _ in metrics),
            *(cm(row[f"{d}_m"]) for d in distances),
        ]
        for name, run in by_name.items()
        for row in run["scores"]
        if name != BEFORE_ROWS or row["region"] == "global"
    ]
    return table(" | ".join(header), rows)


def _cost_table(by_name: dict[str, dict]) -> list[str]:
    rows = []
    for name, run in by_name.items():
        cost = run["cost"]
        file_mb = cost.get("map_file_bytes")
        rows.append(
            [
                name,
                f"{cost['wall_s']:.1f}",
                f"{cost['mesh_s']:.1f}",
                "-" if file_mb is None else f"{file_mb / 1e6:.2f}",
                f"{cost['map_memory_bytes'] / 1e6:.1f}",
                f"{cost['peak_rss_mb']:.0f}",
            ]
        )
    header = "map | build [s] | mesh [s] | `map.npz` [MB] | memory [MB] | peak RSS [MB]"
    return table(header, rows)


def _row(run: dict, region: str, range_m: float) -> dict:
    return next(r for r in run["scores"] if r["region"] == region and r["range_m"] == range_m)


def target_lines(by_name: dict[str, dict], range_m: float) -> list[str]:
    """Targets of the neural map over the surface observed within ``range_m`` (ground-truth
    poses): recall at 10 cm at least the TSDF's, precision at 10 cm at least 0.9, ``map.npz`` at
    most a tenth of the TSDF's memory, wall time and peak RSS at most 1.3x the before run's."""
    if "neural map" not in by_name or "TSDF" not in by_name:
        return []
    ours, tsdf = by_name["neural map"], by_name["TSDF"]
    mine, theirs = _row(ours, "global", range_m), _row(tsdf, "global", range_m)
    file_share = ours["cost"]["map_file_bytes"] / tsdf["cost"]["map_memory_bytes"]
    checks = [
        (
            f"recall at 10 cm {mine['recall_0.1']:.3f} vs the TSDF's {theirs['recall_0.1']:.3f}",
            mine["recall_0.1"] >= theirs["recall_0.1"],
        ),
        (
            f"precision at 10 cm {mine['precision_0.1']:.3f} (>= {TARGET_PRECISION})",
            mine["precision_0.1"] >= TARGET_PRECISION,
        ),
        (
            f"`map.npz` {file_share:.3f} of the TSDF's memory (<= {TARGET_FILE_SHARE})",
            file_share <= TARGET_FILE_SHARE,
        ),
    ]
    before = by_name.get(BEFORE_ROWS)
    for key, label in (("wall_s", "wall time"), ("peak_rss_mb", "peak RSS")) if before else ():
        ratio = ours["cost"][key] / before["cost"][key]
        checks.append(
            (
                f"{label} {ratio:.2f}x the before run's (<= {TARGET_RSS_WALL_RATIO}x)",
                ratio <= TARGET_RSS_WALL_RATIO,
            )
        )
    return [
        f"Targets over the surface observed within {range_m:g} m (ground-truth poses, global):",
        "",
        *(f"- {text}: {'met' if ok else 'missed'}" for text, ok in checks),
        "",
    ]


def report_lines(
    results: dict[str, Any],
    *,
    window: str,
    mulran_frames: int | None,
    stretch_scans: int,
    variants: dict[str, list[str]],
    sensor_range_m: float,
    tsdf_voxel_m: float,
) -> list[str]:
    """The section below its header."""
    lines = [
        f"- Scans: {window}, configs/kitti.yaml"
        + "".join(
            f"; {name}: `{' '.join(sets) or 'as configured'}`" for name, sets in variants.items()
        ),
        f"- Observed surface: ground-truth mesh samples within {cm(OBSERVED_DISTANCE_M)} cm of "
        f"a scan point of lower range than the limit (points placed by the ground-truth poses, "
        f"averaged on a {cm(OBSERVED_POINT_VOXEL_M)} cm grid). Precision and accuracy over the "
        "map's surface within the limit of a sensor position; recall and completion over the "
        "observed samples. P / R / F @ d: precision, recall, F-score at d cm.",
        f"- TSDF: {cm(tsdf_voxel_m)} cm voxels, truncation 3 voxels, the scans' points within "
        f"{sensor_range_m:g} m at the same poses (benchmarks/harness/lidar_tsdf.py); memory: the "
        "8^3-voxel blocks it allocates at 8 bytes a voxel. Build: the pipeline's wall time "
        "(neural map) or the integration (TSDF); peak RSS of the run's own process.",
        f"- SLAM rows: the mesh aligned by the SE(3) alignment of the run's poses onto the ground "
        f"truth over all scans (global), and over each stretch of {stretch_scans} scans alone.",
        f"- Took {results['seconds']:.0f} s.",
        "",
    ]
    for kind, by_name in results["runs"].items():
        title = KIND_TITLES[kind]
        if kind == "mulran":
            count = "all" if mulran_frames is None else f"the first {mulran_frames}"
            title += f", {count} keyframes, configs/lidar.yaml"
        lines += [
            f"### {title}",
            "",
            *_quality_table(by_name, points_only=kind == "mulran"),
            "",
            *_cost_table(by_name),
            "",
        ]
        if kind == "gt":
            lines += target_lines(by_name, sensor_range_m)
    return lines
