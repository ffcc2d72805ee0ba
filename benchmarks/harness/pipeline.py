"""One whole-pipeline run in this process, as the accuracy, SLAM and variant benchmarks make it
(:func:`run_pipeline`), and what they read from the finished pipeline against the ground truth
(:func:`trajectory_summary`).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

QUIET = {
    "viz": {"mode": "none", "mesh_every_submaps": 10**9, "mesh_after_remap": False},
    "mapping": {"device": "cpu"},
}
"""Overrides of every benchmark run: no viewer, no periodic meshes, the map on the CPU."""


def add_override_arguments(parser, rows: str) -> None:
    """``--set KEY=VALUE`` (run config overrides, into ``sets``) and ``--before-set KEY=VALUE``
    (into ``before_sets``: the same runs again with these too, shown as the "before" ``rows``)."""
    parser.add_argument(
        "--set", dest="sets", action="append", default=[], help="run config override KEY=VALUE"
    )
    parser.add_argument(
        "--before-set",
        dest="before_sets",
        action="append",
        default=[],
        help=f"also run with this override KEY=VALUE on top, as the {rows}",
    )


def load_config(config_name: str, overrides: dict[str, Any] | None = None):
    """``configs/<config_name>.yaml`` with :data:`QUIET` and ``overrides`` on top."""
    from slam.assembly.config import default_config_path, load_run_config, merge_overrides

    path = default_config_path(config_name)
    return load_run_config(path, merge_overrides(QUIET, overrides or {}))


def run_pipeline(cfg, source, odometry=None) -> tuple[Any, float]:
    """Every frame of ``source`` through a finished pipeline (one torch thread; ``odometry``:
    the config's for the source's sensor unless given): ``(pipeline, wall seconds)``."""
    import torch

    from slam.algorithm.pipeline import SlamPipeline
    from slam.assembly.builders import build_map, build_odometry

    torch.set_num_threads(1)
    logging.basicConfig(level=logging.WARNING)
    if odometry is None:
        odometry = build_odometry(cfg, source.sensor)
    pipeline = SlamPipeline(cfg.pipeline_config(), source.sensor, odometry, build_map(cfg))
    start = time.perf_counter()
    for frame in source.read_ahead():
        pipeline.process(frame)
    pipeline.finish()
    return pipeline, time.perf_counter() - start


def anchor_frames(pipeline, loop) -> tuple[int, int]:
    """The anchor frames of a loop's reference and query submaps."""
    frames = pipeline.frames
    return frames.submap_frames(loop.reference_id)[0], frames.submap_frames(loop.query_id)[0]


def loop_errors(pipeline, gt: np.ndarray) -> list[tuple[float, float, bool]]:
    """(translation m, rotation deg, kept by the graph) of every verified loop against the
    ground-truth relative pose of its anchors."""
    from common.geometry import relative_motion

    errors = []
    for c in pipeline.accepted_loops():
        a, b = anchor_frames(pipeline, c)
        m, d = relative_motion(np.linalg.inv(gt[a]) @ gt[b], c.T_Ai_Aj)
        errors.append((m, d, bool(c.graph_inlier)))
    return errors


def rejections(pipeline) -> dict[str, int]:
    """Rejected loop candidates, counted by the first word of their reason."""
    counts: dict[str, int] = {}
    for c in pipeline.loop_candidates:
        if not c.accepted:
            key = c.reason.split(":")[0].split(" ")[0] if c.reason else "?"
            counts[key] = counts.get(key, 0) + 1
    return counts


def trajectory_summary(pipeline, gt: np.ndarray, wall_s: float) -> dict[str, Any]:
    """Loops, ATE (whole and per world axis) of the odometry and of SLAM, SLAM's unaligned
    errors in the first pose's frame (``unaligned_slam``: position RMSE m, mean |yaw| and mean
    tilt deg), wall time, frames/s and the seconds per pipeline stage."""
    from dataclasses import astuple

    from slam.evaluation.metrics.trajectory import ate_per_axis_rmse, ate_rmse, unaligned_error

    errors = loop_errors(pipeline, gt)
    odometry, slam = pipeline.frames.odometry_poses(), pipeline.slam_poses()
    return {
        "frames": len(pipeline.frames),
        "submaps": len(pipeline.records),
        "candidates": len(pipeline.loop_candidates),
        "verified": len(errors),
        "kept": sum(1 for *_, kept in errors if kept),
        "loop_errors": errors,
        "rejections": rejections(pipeline),
        "ate_odometry_m": ate_rmse(odometry, gt),
        "ate_slam_m": ate_rmse(slam, gt),
        "ate_xyz_odometry_m": ate_per_axis_rmse(odometry, gt).tolist(),
        "ate_xyz_slam_m": ate_per_axis_rmse(slam, gt).tolist(),
        "unaligned_slam": list(astuple(unaligned_error(slam, gt))),
        "wall_s": wall_s,
        "fps": len(pipeline.frames) / wall_s,
        "stage_s": {k: float(sum(v)) for k, v in pipeline.timings_s.items()},
    }
