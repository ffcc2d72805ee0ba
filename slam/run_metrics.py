"""The numbers of a finished run (``metrics.json``): trajectory and mesh errors against ground
truth where it exists, loop and remap counts, timing and memory.

Mesh metrics compare the final mesh with the ground-truth mesh after moving the mesh into the
ground-truth world with the same SE(3) Umeyama alignment as the ATE (estimated positions onto
ground-truth positions); for RGB-D runs completion only counts ground-truth faces inside the
view frustum of at least one ground-truth camera.
"""

from __future__ import annotations

import logging
import resource
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from slam.pipeline import SlamPipeline

logger = logging.getLogger(__name__)


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def loop_summary(pipeline: SlamPipeline) -> dict[str, Any]:
    """Counts of loop candidates by outcome (reasons are grouped by their first word)."""
    candidates = pipeline.loop_candidates
    verified = [c for c in candidates if c.accepted]
    reasons = Counter(c.reason.split(" ")[0] for c in candidates if not c.accepted)
    return {
        "candidates": len(candidates),
        "verified": len(verified),
        "graph_inliers": sum(1 for c in verified if c.graph_inlier),
        "graph_outliers": sum(1 for c in verified if c.graph_inlier is False),
        "rejected": len(candidates) - len(verified),
        "rejected_by": dict(reasons),
    }


def remap_summary(pipeline: SlamPipeline) -> dict[str, Any]:
    """Remapping passes, submaps moved and their throughput."""
    events = pipeline.remapper.events
    moved = sum(e.num_moved for e in events)
    seconds = sum(e.seconds for e in events)
    return {
        "events": len(events),
        "submaps_moved": moved,
        "seconds_total": seconds,
        "seconds_per_event_max": max((e.seconds for e in events), default=0.0),
        "submaps_per_s": moved / seconds if seconds > 0 else None,
        "frames_moved": sum(len(pipeline.submap_frames(i)) for e in events for i in e.moved_ids),
    }


def timing_summary(pipeline: SlamPipeline, wall_s: float) -> dict[str, Any]:
    """Wall time, frame rate and per-stage time."""
    stages = {
        name: {
            "calls": len(values),
            "mean_ms": 1e3 * float(np.mean(values)),
            "total_s": sum(values),
        }
        for name, values in pipeline.timings_s.items()
        if values
    }
    return {
        "wall_s": wall_s,
        "frames_per_s": pipeline.num_frames / wall_s if wall_s > 0 else None,
        "stages": stages,
    }


def near_trajectory_mask(
    mesh: trimesh.Trimesh, positions: np.ndarray, radius_m: float
) -> np.ndarray:
    """Faces whose centroid lies within ``radius_m`` of a sensor position (LiDAR coverage)."""
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(np.asarray(positions)).query(mesh.triangles_center, k=1)
    return distance <= radius_m


def mesh_errors(
    mesh: trimesh.Trimesh,
    gt_mesh_path: Path,
    T_gt_W: np.ndarray,
    num_samples: int,
    gt_poses: np.ndarray,
    cameras: tuple[np.ndarray, int, int] | None = None,
    lidar_range_m: float | None = None,
) -> dict[str, Any]:
    """Accuracy / completion of ``mesh`` (world frame W) against the ground-truth mesh file.

    Completion only counts ground-truth faces the sensor could have seen: inside the frustum of
    a ground-truth camera (``cameras = (K, width, height)``), or within ``lidar_range_m`` of a
    ground-truth LiDAR position.
    """
    from slam.metrics.mesh import mesh_metrics, visible_face_mask

    gt = trimesh.load(gt_mesh_path, force="mesh", process=False)
    pred = mesh.copy()
    pred.apply_transform(T_gt_W)
    mask = None
    if cameras is not None:
        K, width, height = cameras
        mask = visible_face_mask(gt, gt_poses[:: max(1, len(gt_poses) // 200)], K, width, height)
    elif lidar_range_m is not None:
        mask = near_trajectory_mask(gt, gt_poses[:, :3, 3], lidar_range_m)
    if mask is not None and not mask.any():
        mask = None
    result = mesh_metrics(pred, gt, num_samples=num_samples, gt_face_mask=mask)
    out = dict(result.__dict__)
    out["gt_mesh"] = str(gt_mesh_path)
    out["completion_seen_only"] = mask is not None
    return out


def collect_metrics(
    pipeline: SlamPipeline,
    *,
    wall_s: float,
    mesh: trimesh.Trimesh | None,
    gt_mesh_path: Path | None,
    intrinsics=None,
    lidar_range_m: float | None = None,
    num_mesh_samples: int = 100_000,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Everything ``metrics.json`` holds."""
    from slam.metrics.trajectory import align_se3, kitti_lengths_within, trajectory_metrics

    metrics: dict[str, Any] = dict(extra or {})
    metrics["num_frames"] = pipeline.num_frames
    metrics["num_submaps"] = len(pipeline.submaps)
    metrics["loops"] = loop_summary(pipeline)
    metrics["remap"] = remap_summary(pipeline)
    submaps = list(pipeline.submaps.values())
    stored_voxels = sum(s.original.num_voxels for s in submaps)
    metrics["map"] = {
        "voxels": int(pipeline.map.num_voxels),
        "memory_bytes": int(pipeline.map.memory_bytes()),
        "submap_voxels": int(stored_voxels),
        "submap_bytes": int(sum(s.nbytes() for s in submaps)),
        # how many times each global voxel is stored among the submaps (submap overlap)
        "overlap": stored_voxels / max(pipeline.map.num_voxels, 1),
    }
    gt = pipeline.gt_poses()
    slam = pipeline.slam_poses()
    if gt is not None and len(gt) >= 2:
        lengths = kitti_lengths_within(gt)
        quiet = logging.getLogger("slam.metrics.trajectory")
        level = quiet.level
        quiet.setLevel(logging.ERROR)  # "too short for the KITTI error" is expected here
        try:
            metrics["trajectory"] = {
                "odometry": trajectory_metrics(
                    pipeline.odometry_poses(), gt, kitti_lengths_m=lengths
                ).as_dict(),
                "slam": trajectory_metrics(slam, gt, kitti_lengths_m=lengths).as_dict(),
            }
        finally:
            quiet.setLevel(level)
    if mesh is not None and gt_mesh_path is not None and gt is not None:
        T_gt_W = align_se3(slam, gt)
        cameras = None
        if intrinsics is not None:
            cameras = (intrinsics.K, intrinsics.width, intrinsics.height)
        try:
            metrics["mesh"] = mesh_errors(
                mesh,
                gt_mesh_path,
                T_gt_W,
                num_mesh_samples,
                gt,
                cameras=cameras,
                lidar_range_m=None if cameras is not None else lidar_range_m,
            )
        except ValueError as exc:
            logger.warning("mesh metrics skipped: %s", exc)
    metrics["timing"] = timing_summary(pipeline, wall_s)
    metrics["memory"] = {"peak_rss_mb": peak_rss_mb()}
    return metrics
