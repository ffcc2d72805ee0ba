"""End-to-end SLAM benchmark: loop closure, trajectory error, speed, memory and remapping.

    python -m benchmarks.bench_slam [--quick] [--out benchmarks/results/slam.md]
    python -m benchmarks.bench_slam --scenario 7scenes   # -> benchmarks/results/slam_7scenes.md

Scenarios (each in its own process, so that its peak memory is its own):

* LiDAR: a 64-beam LiDAR simulated along the real KITTI 00 ground-truth trajectory (frames
  0-1700 in full mode, every 3rd frame of 0-1650 in quick mode; both contain the revisit of the
  start area from frame 1559 on), run with configs/kitti.yaml, once with KISS-ICP odometry and
  once with ground truth plus an injected yaw drift (a stand-in for a drifting front-end, so that
  the loop closure has something to correct). KISS-SLAM runs side by side when its environment
  exists (``make kiss-slam-env``; see benchmarks/harness/reference.py).
* RGB-D: the generated room loop (configs/demo.yaml) and real 7-Scenes redkitchen seq-01 frames
  0-399 (configs/7scenes.yaml; skipped when ../shared/data is absent). Its ground truth comes
  from KinectFusion, which disagrees with the depth images at revisits by a few cm, so its loop
  edges are also judged against a dense depth registration of their anchor keyframes
  (benchmarks/harness/depth_registration.py).
* Remapping: in the room run every submap keeps its points; after the run a second map is encoded
  from scratch at the final poses and compared with the remapped map; remapping throughput is
  compared with the paper's 50 frames/s.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.harness.child import in_child
from benchmarks.harness.kitti import KITTI_POSES, have_kitti, kitti_source, window
from benchmarks.harness.machine import machine_line
from benchmarks.harness.paths import DATA, RESULTS_DIR
from benchmarks.harness.reference import KISS_SLAM_VERSION, kiss_slam
from benchmarks.slam_report import write_7scenes_report, write_report
from benchmarks.slam_tables import fmt as _fmt
from common.atomic_io import write_text_atomic
from frontends.odometry.base import Odometry, OdometryResult

FULL_LIDAR_FRAMES = 1700
"""Full mode's LiDAR window: the first 1,700 poses (the revisit of the start is at 1559)."""
DRIFT_TOTAL_DEG = 1.65
"""Injected yaw drift over the LiDAR window (the revisit stays within the proximity radius)."""

log = logging.getLogger("benchmarks.bench_slam")


# --------------------------------------------------------------------------- helpers


class DriftingOdometry(Odometry):
    """Ground-truth increments with a constant yaw bias per frame (z up)."""

    def __init__(self, yaw_deg_per_frame: float) -> None:
        from frontends.odometry.ground_truth import GroundTruthOdometry

        self._gt = GroundTruthOdometry()
        self._previous = None
        self._pose = np.eye(4)
        a = np.radians(yaw_deg_per_frame)
        self._bias = np.eye(4)
        self._bias[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]

    def register(self, frame) -> OdometryResult:
        T = self._gt.register(frame).T_W_S
        if self._previous is not None:
            self._pose = self._pose @ (np.linalg.inv(self._previous) @ T) @ self._bias
        self._previous = T
        return OdometryResult(self._pose.copy())


def _peak_rss_mb() -> float:
    from slam.evaluation.run_metrics import peak_rss_mb

    return peak_rss_mb()


def _loop_errors(pipeline, gt: np.ndarray) -> list[tuple[float, float]]:
    """Error of every verified loop edge against the ground-truth relative anchor pose."""
    from common.geometry import relative_motion

    errors = []
    for c in pipeline.accepted_loops():
        a = pipeline.submap_frames(c.reference_id)[0]
        b = pipeline.submap_frames(c.query_id)[0]
        truth = np.linalg.inv(gt[a]) @ gt[b]
        errors.append(relative_motion(truth, c.T_Ai_Aj))
    return errors


def _run(cfg, source, odometry) -> tuple[Any, float]:
    from slam.algorithm.pipeline import SlamPipeline
    from slam.assembly.builders import build_map

    neural_map = build_map(cfg)
    pipeline = SlamPipeline(cfg.pipeline_config(), source.sensor, odometry, neural_map)
    start = time.perf_counter()
    for frame in source.read_ahead():
        pipeline.process(frame)
    pipeline.finish()
    return pipeline, time.perf_counter() - start


def _summary(pipeline, wall_s: float, gt: np.ndarray) -> dict:
    from slam.evaluation.metrics.trajectory import ate_per_axis_rmse, ate_rmse

    errors = _loop_errors(pipeline, gt)
    events = pipeline.remapper.events
    verified = pipeline.accepted_loops()
    return {
        "frames": pipeline.num_frames,
        "submaps": len(pipeline.submaps),
        "candidates": len(pipeline.loop_candidates),
        "verified": len(verified),
        "kept": sum(1 for c in verified if c.graph_inlier),
        "loop_errors": [[m, d] for m, d in errors],
        "loop_kept": [bool(c.graph_inlier) for c in verified],
        "ate_odometry_m": ate_rmse(pipeline.odometry_poses(), gt),
        "ate_slam_m": ate_rmse(pipeline.slam_poses(), gt),
        "ate_xyz_odometry_m": ate_per_axis_rmse(pipeline.odometry_poses(), gt).tolist(),
        "ate_xyz_slam_m": ate_per_axis_rmse(pipeline.slam_poses(), gt).tolist(),
        "wall_s": wall_s,
        "fps": pipeline.num_frames / wall_s,
        "remap_events": len(events),
        "remap_moved": sum(e.num_moved for e in events),
        "remap_frames_moved": sum(
            len(pipeline.submap_frames(i)) for e in events for i in e.moved_ids
        ),
        "remap_s_total": sum(e.seconds for e in events),
        "remap_s_max": max((e.seconds for e in events), default=0.0),
        "map_voxels": pipeline.map.num_voxels,
        "stage_s": {k: float(sum(v)) for k, v in pipeline.timings_s.items()},
    }


def _mesh_accuracy(pipeline, source, num_samples: int = 100_000) -> dict | None:
    from slam.evaluation.run_metrics import mesh_errors

    if source.gt_mesh_path is None:
        return None
    from slam.evaluation.metrics.trajectory import align_se3

    gt = source.gt_poses
    frame = source[0]
    cameras = None
    lidar_range = None
    if frame.intrinsics is not None:
        cameras = (frame.intrinsics.K, frame.intrinsics.width, frame.intrinsics.height)
    else:
        lidar_range = pipeline.cfg.submaps.max_range_m
    T = align_se3(pipeline.slam_poses(), gt)
    return mesh_errors(
        pipeline.map.extract_mesh(),
        source.gt_mesh_path,
        T,
        num_samples,
        gt,
        cameras=cameras,
        lidar_range_m=lidar_range,
    )


def _child_setup() -> None:
    import torch

    torch.set_num_threads(1)
    logging.basicConfig(level=logging.WARNING)


# --------------------------------------------------------------------------- scenarios


def lidar_frames(quick: bool) -> int:
    """Scans of the LiDAR window: the whole quick window, or the first 1,700 full-window poses."""
    return window(quick).num_frames if quick else FULL_LIDAR_FRAMES


def lidar_source(quick: bool):
    return kitti_source(quick, lidar_frames(quick))


def scenario_lidar(quick: bool, odometry_mode: str) -> dict:
    """One LiDAR run with configs/kitti.yaml."""
    _child_setup()
    from slam.assembly.builders import build_odometry
    from slam.assembly.config import default_config_path, load_run_config

    source = lidar_source(quick)
    overrides: dict[str, Any] = {
        "source": {"dataset": "generated"},
        "viz": {"mode": "none", "mesh_every_submaps": 10**9, "mesh_after_remap": False},
        "mapping": {"device": "cpu"},
    }
    cfg = load_run_config(default_config_path("kitti"), overrides)
    if odometry_mode == "kiss-icp":
        odometry = build_odometry(cfg, "lidar")
    else:
        odometry = DriftingOdometry(DRIFT_TOTAL_DEG / lidar_frames(quick))
    pipeline, wall = _run(cfg, source, odometry)
    out = _summary(pipeline, wall, source.gt_poses)
    mesh = _mesh_accuracy(pipeline, source, num_samples=50_000)
    out["mesh_accuracy_m"] = None if mesh is None else mesh["accuracy_m"]
    out["mesh_completion_m"] = None if mesh is None else mesh["completion_m"]
    out["sequence_dir"] = str(source.sequence_dir)
    out["peak_rss_mb"] = _peak_rss_mb()
    return out


def scenario_room() -> dict:
    _child_setup()
    from frontends.sources import make_source
    from slam.assembly.builders import build_map, build_odometry
    from slam.assembly.config import default_config_path, load_run_config
    from slam.assembly.datasets import source_kwargs
    from slam.evaluation.metrics.mesh import mesh_metrics

    cfg = load_run_config(
        default_config_path("demo"),
        {
            "submaps": {"keep_points": True},
            "viz": {"mode": "none", "mesh_every_submaps": 10**9, "mesh_after_remap": False},
            "remap": {"translation_threshold_m": 0.002, "rotation_threshold_deg": 0.1},
            "mapping": {"device": "cpu"},
        },
    )
    source = make_source("generated", **source_kwargs(cfg))
    pipeline, wall = _run(cfg, source, build_odometry(cfg, "rgbd"))
    out = _summary(pipeline, wall, source.gt_poses)
    out["peak_rss_mb"] = _peak_rss_mb()
    mesh = _mesh_accuracy(pipeline, source)
    out["mesh_accuracy_m"] = mesh["accuracy_m"]
    out["mesh_completion_m"] = mesh["completion_m"]
    out["mesh_completion_ratio"] = mesh["completion_ratio"]

    # Remapping equivalence: the remapped map vs a map encoded from scratch at the final poses.
    final = pipeline.graph.poses()
    scratch = build_map(cfg)
    start = time.perf_counter()
    for submap_id, record in pipeline.records.items():
        scratch.fuse(scratch.encode(submap_id, record.points_A, record.normals_A, final[submap_id]))
    out["scratch_encode_s"] = time.perf_counter() - start
    out["scratch_encode_points"] = int(sum(len(r.points_A) for r in pipeline.records.values()))
    distance = mesh_metrics(
        pipeline.map.extract_mesh(), scratch.extract_mesh(), num_samples=100_000
    )
    out["remap_vs_scratch_m"] = (distance.accuracy_m, distance.completion_m)
    out["remap_vs_scratch_median_m"] = (distance.accuracy_median_m, distance.completion_median_m)
    moved = [s for s in pipeline.submaps.values() if s.is_moved]
    out["moved_submap_voxels_mean"] = (
        float(np.mean([s.original.num_voxels for s in moved])) if moved else None
    )
    # Throughput of moving every submap once more (remove, transform, fuse), from the final map.
    start = time.perf_counter()
    for submap_id, submap in pipeline.submaps.items():
        T = final[submap_id].copy()
        T[:3, 3] += [0.013, -0.007, 0.004]
        pipeline.map.move(submap, T)
    seconds = time.perf_counter() - start
    out["move_all_s"] = seconds
    out["move_all_submaps"] = len(pipeline.submaps)
    out["move_all_frames"] = pipeline.num_frames
    return out


def scenario_7scenes() -> dict | None:
    _child_setup()
    if not (DATA / "7scenes_redkitchen").is_dir():
        return None
    from frontends.sources import make_source
    from slam.assembly.builders import build_odometry
    from slam.assembly.config import default_config_path, load_run_config
    from slam.assembly.datasets import source_kwargs

    cfg = load_run_config(
        default_config_path("7scenes"),
        {
            "source": {"root": str(DATA / "7scenes_redkitchen"), "sequence": "seq-01"},
            "viz": {"mode": "none", "mesh_every_submaps": 10**9, "mesh_after_remap": False},
            "mapping": {"device": "cpu"},
        },
    )
    from benchmarks.harness.depth_registration import judge_loop_edges

    source = make_source("7scenes", **source_kwargs(cfg))
    pipeline, wall = _run(cfg, source, build_odometry(cfg, "rgbd"))
    out = _summary(pipeline, wall, source.gt_poses)
    out["peak_rss_mb"] = _peak_rss_mb()  # before the dense registrations below
    start = time.perf_counter()
    out["loop_dense"] = judge_loop_edges(
        pipeline, source, max_depth_m=cfg.odometry.rgbd.max_depth_m
    )
    out["loop_dense_s"] = time.perf_counter() - start
    return out


def scenario_kiss_slam(quick: bool) -> dict:
    """KISS-SLAM (own environment, default config) on the same generated sequence."""
    out = kiss_slam(lidar_source(quick), lidar_frames(quick))
    if "skipped" in out:
        return out
    out["summary"] = (
        f"KISS-SLAM {KISS_SLAM_VERSION} (default config; its KITTI loader applies the 0.22 deg "
        "vertical-angle correction that the generated scans do not need) on the same sequence: "
        f"ATE {out['ate_slam_m']:.3f} m (our ATE definition), closures reported "
        f"{_fmt(out['closures'], digits=0)}, {out['fps']:.1f} frames/s over the whole process "
        f"({_fmt(out['own_frequency_hz'], digits=0)} Hz as it reports per scan), peak RSS "
        f"{out['peak_rss_mb']:.0f} MB."
    )
    return out


# --------------------------------------------------------------------------- report


def _write_report(path: Path, results: dict, quick: bool, command: str) -> None:
    window_text = window(quick).describe(lidar_frames(quick))
    write_report(path, results, command, window_text, DRIFT_TOTAL_DEG)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="smaller LiDAR window, no drift run, no 7-Scenes"
    )
    parser.add_argument(
        "--scenario",
        choices=("all", "7scenes"),
        default="all",
        help="all (default) or only real 7-Scenes (its report goes to slam_7scenes.md by default)",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="report (default benchmarks/results/slam.md)"
    )
    parser.add_argument("--skip-kiss-slam", action="store_true", help="do not run KISS-SLAM")
    parser.add_argument(
        "--report-only", action="store_true", help="rewrite the section from the saved .json"
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    only_7scenes = args.scenario == "7scenes"
    if args.out is None:
        args.out = RESULTS_DIR / ("slam_7scenes.md" if only_7scenes else "slam.md")
    raw = args.out.with_suffix(".json")
    command = "python -m benchmarks.bench_slam" + (" --quick" if args.quick else "")
    if only_7scenes:
        command = "python -m benchmarks.bench_slam --scenario 7scenes"
    if args.report_only:
        saved = json.loads(raw.read_text())
        if saved.get("scenario") == "7scenes":
            write_7scenes_report(args.out, saved, saved.get("command", command))
        else:
            _write_report(
                args.out, saved, saved.get("quick", args.quick), saved.get("command", command)
            )
        return 0
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    if only_7scenes:
        results = {
            "machine": machine_line() + "; torch 1 thread, CPU only",
            "scenario": "7scenes",
            "command": command,
        }
        log.info("7-Scenes")
        results["7scenes"] = in_child(scenario_7scenes)
        raw.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(raw, json.dumps(results, indent=2, default=str))
        write_7scenes_report(args.out, results, command)
        log.info("wrote %s", args.out)
        return 0
    results: dict[str, Any] = {
        "machine": machine_line() + "; torch 1 thread per run, CPU only",
        "quick": args.quick,
        "command": command,
    }
    if have_kitti():
        log.info("LiDAR, KISS-ICP")
        results["lidar_kiss"] = in_child(scenario_lidar, args.quick, "kiss-icp")
        if not args.quick:  # quick: KISS-ICP odometry only
            log.info("LiDAR, drifting ground truth")
            results["lidar_drift"] = in_child(scenario_lidar, args.quick, "drift")
        if not args.skip_kiss_slam:
            log.info("KISS-SLAM")
            results["kiss_slam"] = scenario_kiss_slam(args.quick)
    else:
        log.warning("no %s: LiDAR scenarios skipped", KITTI_POSES)
    log.info("RGB-D room")
    results["room"] = in_child(scenario_room)
    if not args.quick:
        log.info("7-Scenes")
        results["7scenes"] = in_child(scenario_7scenes)
    raw.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(raw, json.dumps(results, indent=2, default=str))
    _write_report(args.out, results, args.quick, command)
    log.info("wrote %s", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
