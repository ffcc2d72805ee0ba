"""The numbers of a finished run (``metrics.json``): trajectory and mesh errors against ground
truth where it exists, loop and remap counts, timing and memory.

Trajectory metrics score the frames that have a ground-truth pose (every frame was processed).

Mesh metrics compare the final mesh with the ground-truth mesh after moving the mesh into the
ground-truth world with the same SE(3) Umeyama alignment as the ATE (estimated positions onto
ground-truth positions). Completion counts the ground-truth surface the run observed
(``culling: observed``): faces of the ground truth, subdivided to edges of at most one map
voxel, whose centroid lies within one map voxel of a voxel of the final map (a voxel exists
only where points were fused). ``mesh_unculled`` keeps the looser number, labelled as such:
RGB-D runs count every face in the view frustum of a ground-truth camera (occluded and
out-of-range surfaces included), LiDAR runs every face within the submap range of the
trajectory.
"""

from __future__ import annotations

import logging
import math
import resource
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from frontends.frame import Intrinsics
from slam.algorithm.report import PipelineReport

logger = logging.getLogger(__name__)


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def loop_summary(report: PipelineReport) -> dict[str, Any]:
    """Counts of loop candidates by outcome (reasons are grouped by their first word)."""
    candidates = report.loop_candidates
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


def remap_summary(report: PipelineReport) -> dict[str, Any]:
    """Remapping passes, submaps moved and their throughput."""
    events = report.remap_events
    moved = sum(e.num_moved for e in events)
    seconds = sum(e.seconds for e in events)
    return {
        "events": len(events),
        "submaps_moved": moved,
        "seconds_total": seconds,
        "seconds_per_event_max": max((e.seconds for e in events), default=0.0),
        "submaps_per_s": moved / seconds if seconds > 0 else None,
        "frames_moved": sum(
            report.submap_frame_counts.get(i, 0) for e in events for i in e.moved_ids
        ),
    }


def timing_summary(
    report: PipelineReport,
    wall_s: float,
    pipeline_s: float | None = None,
    setup_s: float | None = None,
) -> dict[str, Any]:
    """Wall time, the pipeline's frame rate and per-stage time (wall, and CPU seconds of the
    thread that ran the stage: the map worker's for mapping and remap).

    ``pipeline_s`` is the time from the first frame read to the end of the final optimisation
    (reading frames included); ``frames_per_s`` is frames / ``pipeline_s``. ``wall_s`` also holds
    ``setup_s`` (building the source, which may generate data; models) and the final mesh, map
    and metrics.
    """
    if pipeline_s is None:
        pipeline_s = wall_s
    stages = {
        name: {
            "calls": len(values),
            "mean_ms": 1e3 * float(np.mean(values)),
            "total_s": sum(values),
            "cpu_s": report.stage_cpu_s.get(name),
        }
        for name, values in report.timings_s.items()
        if values
    }
    return {
        "wall_s": wall_s,
        "setup_s": setup_s,
        "pipeline_s": pipeline_s,
        "frames_per_s": report.num_frames / pipeline_s if pipeline_s > 0 else None,
        "stages": stages,
    }


def near_trajectory_mask(
    mesh: trimesh.Trimesh, positions: np.ndarray, radius_m: float
) -> np.ndarray:
    """Faces whose centroid lies within ``radius_m`` of a sensor position (LiDAR coverage)."""
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(np.asarray(positions)).query(mesh.triangles_center, k=1)
    return distance <= radius_m


def unculled_face_mask(
    gt: trimesh.Trimesh,
    gt_poses: np.ndarray,
    intrinsics: Intrinsics | None = None,
    lidar_range_m: float | None = None,
) -> tuple[np.ndarray | None, str]:
    """Ground-truth faces the sensor could have seen, and the culling's name: in the frustum of a
    ground-truth camera with ``intrinsics``, else within ``lidar_range_m`` of a ground-truth
    LiDAR position; None (and ``"none"``) when neither applies or nothing is kept."""
    from slam.evaluation.metrics.mesh import visible_face_mask

    mask, name = None, "none"
    if intrinsics is not None:
        poses = gt_poses[:: max(1, len(gt_poses) // 200)]
        mask = visible_face_mask(gt, poses, intrinsics.K, intrinsics.width, intrinsics.height)
        name = "frustum"
    elif lidar_range_m is not None:
        mask = near_trajectory_mask(gt, gt_poses[:, :3, 3], lidar_range_m)
        name = f"within {lidar_range_m} m of the trajectory"
    if mask is not None and not mask.any():
        return None, "none"
    return mask, name


def mesh_errors(
    mesh: trimesh.Trimesh,
    gt_mesh_path: Path,
    T_gt_W: np.ndarray,
    num_samples: int,
    gt_poses: np.ndarray,
    intrinsics: Intrinsics | None = None,
    lidar_range_m: float | None = None,
) -> dict[str, Any]:
    """Accuracy / completion of ``mesh`` (world frame W) against the ground-truth mesh file, with
    completion over the faces of :func:`unculled_face_mask` (frustum or LiDAR range)."""
    from slam.evaluation.metrics.mesh import mesh_metrics

    gt = trimesh.load(gt_mesh_path, force="mesh", process=False)
    pred = mesh.copy()
    pred.apply_transform(T_gt_W)
    mask, culling = unculled_face_mask(gt, gt_poses, intrinsics, lidar_range_m)
    out = mesh_metrics(pred, gt, num_samples=num_samples, gt_face_mask=mask).as_dict()
    out.update(gt_mesh=str(gt_mesh_path), culling=culling, completion_seen_only=mask is not None)
    return out


CULL_MAX_FACES = 8_000_000
"""Observed-surface culling subdivides the ground truth to edges of the cull distance; a distance
that would make more faces than this is refused (8 M faces take about 3.5 GB)."""


class CullDistanceTooSmall(ValueError):
    """The cull distance would subdivide the ground truth into more than :data:`CULL_MAX_FACES`."""


def subdivided_face_count(triangles: np.ndarray, distance_m: float) -> int:
    """Faces that ``trimesh.remesh.subdivide_to_size(max_edge=distance_m, max_iter=12)`` makes of
    ``triangles`` (F, 3, 3): each pass splits a face into 4 until its longest edge fits."""
    edges = np.linalg.norm(triangles - np.roll(triangles, 1, axis=1), axis=2).max(axis=1)
    with np.errstate(divide="ignore"):
        passes = np.ceil(np.log2(np.maximum(edges / distance_m, 1.0)))
    return int(np.sum(4.0 ** np.clip(passes, 0, 12)))


def check_cull_distance(triangles: np.ndarray, distance_m: float) -> None:
    """Raise :class:`CullDistanceTooSmall` (naming the smallest distance that fits) when culling
    at ``distance_m`` would make more than :data:`CULL_MAX_FACES` faces."""
    if not (math.isfinite(distance_m) and distance_m > 0):
        raise CullDistanceTooSmall(f"cull distance {distance_m} m: must be a positive number")
    count = subdivided_face_count(triangles, distance_m)
    if count <= CULL_MAX_FACES:
        return
    smallest = distance_m
    while subdivided_face_count(triangles, smallest) > CULL_MAX_FACES:
        smallest *= 2
    raise CullDistanceTooSmall(
        f"cull distance {distance_m:g} m would subdivide the ground truth into {count:,} faces "
        f"(at most {CULL_MAX_FACES:,}); use at least {smallest:.3g} m"
    )


def observed_face_mask(
    gt_mesh: trimesh.Trimesh, observed_points: np.ndarray, distance_m: float
) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Subdivide ``gt_mesh`` (edges <= ``distance_m``) where it comes near ``observed_points`` and
    mark the faces whose centroid lies within ``distance_m`` of one. Returns ``(mesh, mask)``:
    the same surface as ``gt_mesh`` (faces far from every observation are kept whole, unmarked).

    Edges of ``distance_m / 2`` gave the same demo-room numbers to 0.1 mm with 4x the faces
    (3.8 M; 1.6 GB more memory)."""
    from scipy.spatial import cKDTree

    observed_points = np.asarray(observed_points, dtype=np.float64).reshape(-1, 3)
    if len(observed_points) == 0:
        return gt_mesh, np.zeros(len(gt_mesh.faces), dtype=bool)
    tree = cKDTree(observed_points)
    centers = np.asarray(gt_mesh.triangles_center)
    radius = np.linalg.norm(np.asarray(gt_mesh.triangles) - centers[:, None], axis=2).max(axis=1)
    nearest, _ = tree.query(centers, workers=-1)
    near = nearest <= distance_m + radius
    check_cull_distance(np.asarray(gt_mesh.triangles)[near], distance_m)
    vertices, faces = trimesh.remesh.subdivide_to_size(
        gt_mesh.vertices, gt_mesh.faces[near], max_edge=distance_m, max_iter=12
    )
    fine = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    distance, _ = tree.query(fine.triangles_center, distance_upper_bound=distance_m, workers=-1)
    far = trimesh.Trimesh(vertices=gt_mesh.vertices, faces=gt_mesh.faces[~near], process=False)
    mask = np.concatenate([np.isfinite(distance), np.zeros(len(far.faces), dtype=bool)])
    if len(far.faces) == 0:
        return fine, mask
    return trimesh.util.concatenate([fine, far]), mask


VIEW_RAY_STEP_PX = 4
"""Observed-surface culling of RGB-D runs: one ray every this many pixels of a camera."""
VIEW_CAMERAS_MAX = 60
"""... from at most this many ground-truth cameras, evenly spread over the trajectory."""


def camera_observed_face_mask(
    gt_mesh: trimesh.Trimesh,
    T_W_C: np.ndarray,
    intrinsics: Intrinsics,
    distance_m: float,
    *,
    max_depth_m: float = 10.0,
) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Ground truth a camera saw: rays through a pixel grid of ground-truth cameras hit the
    ground-truth mesh (first hit only, so occluded surface is not counted, nor surface beyond
    ``max_depth_m``); faces of the mesh subdivided to ``distance_m`` are observed when their
    centroid lies within ``distance_m`` of a hit. Returns ``(subdivided mesh, mask)``."""
    K, width, height = intrinsics.K, intrinsics.width, intrinsics.height
    poses = np.asarray(T_W_C, dtype=np.float64)
    poses = poses[np.unique(np.linspace(0, len(poses) - 1, VIEW_CAMERAS_MAX).round().astype(int))]
    u, v = np.meshgrid(
        np.arange(VIEW_RAY_STEP_PX / 2, width, VIEW_RAY_STEP_PX),
        np.arange(VIEW_RAY_STEP_PX / 2, height, VIEW_RAY_STEP_PX),
    )
    rays_C = np.stack(
        [(u.ravel() - K[0, 2]) / K[0, 0], (v.ravel() - K[1, 2]) / K[1, 1], np.ones(u.size)], 1
    )
    rays_C /= np.linalg.norm(rays_C, axis=1, keepdims=True)
    origins = np.repeat(poses[:, :3, 3], len(rays_C), axis=0)
    directions = np.concatenate([rays_C @ T[:3, :3].T for T in poses])
    locations, ray_ids, _ = gt_mesh.ray.intersects_location(
        origins, directions, multiple_hits=False
    )
    depth = np.linalg.norm(locations - origins[ray_ids], axis=1)
    return observed_face_mask(gt_mesh, locations[depth <= max_depth_m], distance_m)


def mesh_sections(
    mesh: trimesh.Trimesh,
    gt_mesh_path: Path,
    T_gt_W: np.ndarray,
    num_samples: int,
    gt_poses: np.ndarray,
    *,
    observed_points_W: np.ndarray | None,
    cull_distance_m: float,
    intrinsics: Intrinsics | None = None,
    lidar_range_m: float | None = None,
    observe: bool = True,
) -> dict[str, Any]:
    """``{"mesh": ..., "mesh_unculled": ...}`` of ``metrics.json`` (see the module docstring).

    Observed surface: with ``intrinsics``, what rays from the ground-truth cameras hit first
    (:func:`camera_observed_face_mask`, ``cull_distance_m`` apart at most); otherwise ground truth
    within ``cull_distance_m`` of ``observed_points_W`` (the final map's voxel centres, world
    frame W). Neither gives the unculled numbers under ``mesh``. Both sections hold the
    ground-truth mesh used and the completion face mask under private keys ``_gt``/``_mask`` for
    plotting; :func:`public` drops them.
    """
    from slam.evaluation.metrics.mesh import mesh_metrics

    gt = trimesh.load(gt_mesh_path, force="mesh", process=False)
    pred = mesh.copy()
    pred.apply_transform(T_gt_W)
    mask, culling = unculled_face_mask(gt, gt_poses, intrinsics, lidar_range_m)
    unculled = mesh_metrics(pred, gt, num_samples=num_samples, gt_face_mask=mask).as_dict()
    unculled.update(gt_mesh=str(gt_mesh_path), culling=culling, _gt=gt, _mask=mask)
    if not observe:
        return {"mesh": unculled}
    if intrinsics is not None:
        fine, observed = camera_observed_face_mask(gt, gt_poses, intrinsics, cull_distance_m)
        culling = "observed (first hits of camera rays)"
    elif observed_points_W is not None and len(observed_points_W):
        points_gt = observed_points_W @ T_gt_W[:3, :3].T + T_gt_W[:3, 3]
        fine, observed = observed_face_mask(gt, points_gt, cull_distance_m)
        culling = "observed (near map voxels)"
    else:
        return {"mesh": unculled}
    if not observed.any():
        logger.warning("no ground-truth surface within %g m of the map", cull_distance_m)
        return {"mesh": unculled}
    section = mesh_metrics(pred, fine, num_samples=num_samples, gt_face_mask=observed).as_dict()
    section.update(
        gt_mesh=str(gt_mesh_path),
        culling=culling,
        cull_distance_m=cull_distance_m,
        observed_gt_area_fraction=float(fine.area_faces[observed].sum() / fine.area),
        _gt=fine,
        _mask=observed,
    )
    return {"mesh": section, "mesh_unculled": unculled}


CAMERA_CULL_DISTANCE_M = 0.05
"""RGB-D observed-surface culling: ground truth within this of a camera ray's hit is observed
(the completion-ratio threshold; rays every VIEW_RAY_STEP_PX pixels are closer than this at the
depths of indoor sequences)."""


def cull_distance(has_cameras: bool, voxel_size_m: float) -> float:
    """Culling distance: :data:`CAMERA_CULL_DISTANCE_M` for cameras, else one map voxel."""
    return CAMERA_CULL_DISTANCE_M if has_cameras else float(voxel_size_m)


def public(section: dict[str, Any]) -> dict[str, Any]:
    """A mesh section without the private plotting entries."""
    return {k: v for k, v in section.items() if not k.startswith("_")}


def gt_subset(estimates: np.ndarray, gt: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """The frames with a finite ground-truth pose: ``(estimates[mask], gt[mask])``, or None
    when fewer than two frames have one."""
    if gt is None:
        return None
    mask = np.isfinite(np.asarray(gt)).all(axis=(1, 2))
    if mask.sum() < 2:
        return None
    return np.asarray(estimates)[mask], np.asarray(gt)[mask]


def sensor_up(sensor: str | None) -> tuple[float, float, float]:
    """The up axis of a sensor's frame, for the unaligned yaw and tilt errors."""
    from slam.evaluation.metrics.trajectory import CAMERA_UP, LIDAR_UP

    return CAMERA_UP if sensor == "rgbd" else LIDAR_UP


def trajectory_section(
    odometry: np.ndarray | None, slam: np.ndarray, gt: np.ndarray, sensor: str | None = None
) -> dict[str, Any] | None:
    """``metrics.json["trajectory"]`` over the frames that have ground truth (NaN rows skipped;
    no ``odometry`` entry without odometry poses, as in a merged run); ``sensor`` ("lidar",
    "rgbd") says which axis is up for the unaligned errors."""
    from slam.evaluation.metrics.trajectory import kitti_lengths_within, trajectory_metrics

    mask = np.isfinite(np.asarray(gt)).all(axis=(1, 2))
    if mask.sum() < 2:
        return None
    gt = np.asarray(gt)[mask]
    lengths = kitti_lengths_within(gt)
    quiet = logging.getLogger("slam.evaluation.metrics.trajectory")
    level = quiet.level
    quiet.setLevel(logging.ERROR)  # "too short for the KITTI error" is expected here
    try:
        named = {"slam": slam} if odometry is None else {"odometry": odometry, "slam": slam}
        section = {
            name: trajectory_metrics(
                np.asarray(poses)[mask], gt, kitti_lengths_m=lengths, up=sensor_up(sensor)
            ).as_dict()
            for name, poses in named.items()
        }
    finally:
        quiet.setLevel(level)
    section["frames_scored"] = int(mask.sum())
    section["frames_without_gt"] = int((~mask).sum())
    return section


def collect_metrics(
    report: PipelineReport,
    *,
    wall_s: float,
    mesh: trimesh.Trimesh | None,
    gt_mesh_path: Path | None,
    pipeline_s: float | None = None,
    setup_s: float | None = None,
    intrinsics: Intrinsics | None = None,
    lidar_range_m: float | None = None,
    num_mesh_samples: int = 100_000,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Everything ``metrics.json`` holds (the mesh scored only when ``num_mesh_samples`` > 0)."""
    from slam.evaluation.metrics.trajectory import align_se3

    slam_peak_rss_mb = peak_rss_mb()  # before scoring, which loads and samples ground truth
    metrics: dict[str, Any] = dict(extra or {})
    metrics["num_frames"] = report.num_frames
    metrics["num_submaps"] = len(report.submaps)
    metrics["loops"] = loop_summary(report)
    metrics["remap"] = remap_summary(report)
    neural_map = report.neural_map
    stored_voxels = sum(s.original.num_voxels for s in report.submaps)
    metrics["map"] = {
        "voxels": int(neural_map.num_voxels),
        "memory_bytes": int(neural_map.memory_bytes()),
        "submap_voxels": int(stored_voxels),
        "submap_bytes": int(sum(s.nbytes() for s in report.submaps)),
        # how many times each global voxel is stored among the submaps (submap overlap)
        "overlap": stored_voxels / max(neural_map.num_voxels, 1),
    }
    gt = report.gt_poses
    slam = report.slam_poses
    sensor = metrics.get("sensor")
    section = None if gt is None else trajectory_section(report.odometry_poses, slam, gt, sensor)
    if section is not None:
        metrics["trajectory"] = section
    can_score = mesh is not None and gt_mesh_path is not None and section is not None
    if can_score and num_mesh_samples > 0:
        slam_scored, gt_scored = gt_subset(slam, gt)
        T_gt_W = align_se3(slam_scored, gt_scored)
        centers, weights = neural_map.voxel_centers()
        observed = np.asarray(centers)[np.asarray(weights) > 0]
        try:
            sections = mesh_sections(
                mesh,
                gt_mesh_path,
                T_gt_W,
                num_mesh_samples,
                gt_scored,
                observed_points_W=observed,
                cull_distance_m=cull_distance(intrinsics is not None, neural_map.voxel_size_m),
                intrinsics=intrinsics,
                lidar_range_m=lidar_range_m,
            )
            metrics.update({name: public(value) for name, value in sections.items()})
        except ValueError as exc:
            logger.warning("mesh metrics skipped: %s", exc)
    metrics["timing"] = timing_summary(report, wall_s, pipeline_s, setup_s)
    metrics["memory"] = {
        "peak_rss_mb": peak_rss_mb(),
        "peak_rss_before_scoring_mb": slam_peak_rss_mb,
    }
    return metrics
