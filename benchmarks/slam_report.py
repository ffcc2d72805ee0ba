"""The Markdown report of ``bench_slam`` (the whole run, or 7-Scenes alone)."""

from __future__ import annotations

from pathlib import Path

from benchmarks.harness.paths import DATA
from benchmarks.slam_tables import cm as _cm
from benchmarks.slam_tables import dense_section, remap_table, stage_table, trajectory_table
from benchmarks.slam_tables import fmt as _fmt
from common.atomic_io import write_text_atomic

PAPER_REMAP_FPS = 50.0

SEVEN_SCENES_NAME = "7-Scenes redkitchen seq-01 0-399"
SEVEN_SCENES_TEXT = (
    "Ground truth: the generated room's own poses; 7-Scenes' are KinectFusion's. A verified "
    "RGB-D loop counts as false beyond 5 cm / 2 deg from the ground truth on the generated room; "
    "on 7-Scenes beyond 10 cm / 5 deg from KinectFusion, because KinectFusion's poses are "
    "themselves cm off what the depth images say at revisits and its colour images are not "
    "registered to depth."
)


def write_7scenes_report(path: Path, results: dict, command: str) -> None:
    """The 7-Scenes part of the report alone (``--scenario 7scenes``)."""
    r = results.get("7scenes")
    lines = [
        "## SLAM end to end (slam/): 7-Scenes only",
        "",
        f"- Command: `{command}`",
        f"- Machine: {results['machine']}",
        "- One process, `NullLogger`, map on the CPU; configs/7scenes.yaml. frames/s is the "
        "whole pipeline, without the dense registrations of the loop check "
        f"({_fmt(r.get('loop_dense_s') if r else None, digits=1)} s after the run).",
        "",
    ]
    if r is None:
        lines.append(f"Skipped: no {DATA / '7scenes_redkitchen'}.")
    else:
        lines += [SEVEN_SCENES_TEXT, ""]
        lines += trajectory_table([(SEVEN_SCENES_NAME, r, (0.10, 5.0))])
        lines += dense_section(SEVEN_SCENES_NAME, r)
    lines.append("")
    write_text_atomic(path, "\n".join(lines))


def write_report(
    path: Path, results: dict, command: str, lidar_window: str, drift_deg: float
) -> None:
    """The whole report; ``lidar_window`` describes the LiDAR run's window of KITTI 00 and
    ``drift_deg`` the yaw drift injected over it."""
    lines = [
        "## SLAM end to end (slam/)",
        "",
        f"- Command: `{command}`",
        f"- Machine: {results['machine']}",
        "- Every run: one process, `NullLogger` (no Rerun recording), map on the CPU; frames/s is "
        "the whole pipeline (reading the data, odometry, keyframing, neural encoding, loop "
        "closure, pose graph, remapping, final mesh).",
        "",
        "### LiDAR: simulated HDL-64E along the real KITTI 00 trajectory",
        "",
        f"{lidar_window} through the generated street scene; "
        "the window contains the revisit of the start area (from frame 1559 on the car passes "
        "the places of frames 112 on again). configs/kitti.yaml: "
        "30 m submaps, V = 1 m, loop candidates from "
        "map_closures and anchor proximity (20 m), verified by ICP and overlap above the ground. "
        "The road follows KITTI 00's real elevation profile (its slopes, crests and dips). "
        "The second row "
        "replaces KISS-ICP by the ground truth with an injected yaw drift, so that the loop "
        "closure has a drift to remove. Per-axis ATE: RMSE along the world x, y and z (up) axes "
        "after the same alignment, KISS-ICP alone (odometry) -> SLAM.",
        "",
    ]
    lidar_rows = [
        (name, results[key], (1.0, 2.0))
        for name, key in (
            ("KISS-ICP odometry", "lidar_kiss"),
            (f"GT + {drift_deg} deg yaw drift over the window", "lidar_drift"),
        )
        if results.get(key)
    ]
    lines += trajectory_table(lidar_rows)
    kiss_slam = results.get("kiss_slam") or {}
    lines += [
        "",
        "KISS-SLAM side by side: " + kiss_slam.get("summary", kiss_slam.get("skipped", "not run")),
        "",
        "Mesh accuracy of the neural map against the generated street: "
        + ", ".join(f"{name}: {_cm(r['mesh_accuracy_m'])} cm" for name, r, _ in lidar_rows)
        + " (V = 1 m). Completion is not reported for LiDAR: the street mesh holds surfaces the "
        "scanner never sees (roofs, building backs, the far side of blocks).",
        "",
        "### RGB-D",
        "",
        SEVEN_SCENES_TEXT,
        "",
    ]
    rgbd_rows = [("generated room (demo config)", results["room"], (0.05, 2.0))]
    if results.get("7scenes"):
        rgbd_rows.append((SEVEN_SCENES_NAME, results["7scenes"], (0.10, 5.0)))
    lines += trajectory_table(rgbd_rows)
    if results.get("7scenes"):
        lines += dense_section(SEVEN_SCENES_NAME, results["7scenes"])
    room = results["room"]
    lines += [
        "",
        f"Room mesh vs ground truth: accuracy {_cm(room['mesh_accuracy_m'])} cm, completion "
        f"{_cm(room['mesh_completion_m'])} cm, completion ratio (< 5 cm) "
        f"{100 * room['mesh_completion_ratio']:.0f} % (ground-truth faces inside a camera "
        "frustum; occluded faces count as missed). 7-Scenes has no ground-truth mesh.",
        "",
        "### Remapping",
        "",
        "Map after remapping vs a map encoded from scratch with the same points at the final poses "
        "(generated room, V = 0.1 m; mean / median distance between the meshes, 100,000 samples "
        "each way):",
        "",
        "| remapped -> scratch mean [cm] | scratch -> remapped mean [cm] | medians [cm] | "
        "re-encoding all submaps from points [s] |",
        "|---|---|---|---|",
        f"| {_cm(room['remap_vs_scratch_m'][0])} | {_cm(room['remap_vs_scratch_m'][1])} | "
        f"{_cm(room['remap_vs_scratch_median_m'][0])} / {_cm(room['remap_vs_scratch_median_m'][1])}"
        f" | {room['scratch_encode_s']:.1f} ({room['scratch_encode_points']} points) |",
        "",
        "Remapping during the runs (remove + transform from the original encoding + fuse):",
        "",
    ]
    plain = [(name, r) for name, r, _ in lidar_rows + rgbd_rows]
    lines += remap_table(plain)
    rate = room["move_all_submaps"] / room["move_all_s"]
    frames_rate = room["move_all_frames"] / room["move_all_s"]
    lines += [
        "",
        f"Moving every submap of the room map once more: {room['move_all_submaps']} submaps "
        f"({room['move_all_frames']} frames, mean {room['moved_submap_voxels_mean'] or 0:.0f} "
        f"voxels per submap) in {room['move_all_s']:.2f} s = {rate:.1f} submaps/s = "
        f"{frames_rate:.0f} frames/s, against the paper's {PAPER_REMAP_FPS:.0f} frames/s "
        "(the paper remaps per frame; here a submap of ~20 frames moves as one).",
        "",
        "### Where the time goes (seconds per stage)",
        "",
    ]
    lines += stage_table(plain)
    lines.append("")
    write_text_atomic(path, "\n".join(lines))
