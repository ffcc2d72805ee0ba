"""``python -m slam.eval RUN_DIR``: recompute the metrics of a finished run and draw its plots.

    python -m slam.eval RUN_DIR [--gt-poses FILE] [--gt-mesh FILE] [--cull-unobserved]
    python -m slam.eval transform --dataset demo [--root DIR] [--frames A:B:STEP]   (see
        slam/transform_experiment.py)

What is recomputed, with the same functions the run used (``slam.metrics``, ``slam.run_metrics``):

- trajectory, for ``odometry`` and ``slam`` (loop-closed): ATE RMSE after SE(3) Umeyama alignment,
  RPE (consecutive frames), KITTI relative error;
- mesh (``mesh.ply``, moved into the ground-truth world by the SLAM trajectory's alignment):
  accuracy, completion and completion ratio (< 5 cm).

Where the ground truth comes from, first match wins:

- poses: ``--gt-poses`` (KITTI or TUM file; TUM is associated by timestamp), then
  ``poses_gt.{kitti,tum}.txt`` in the run folder, then the run's source rebuilt from its
  ``config.yaml`` (``Source.gt_poses`` of the same frames);
- mesh: ``--gt-mesh``, then ``mesh.gt_mesh`` of the run's ``metrics.json``, then the source's
  ``gt_mesh_path``.

Culling of ground truth the run never saw (completion only; accuracy always uses the whole surface):

- default, as the run does: RGB-D runs keep the ground-truth faces whose centroid lies in the view
  frustum of at least one ground-truth camera (``slam.metrics.mesh.visible_face_mask``); LiDAR runs
  keep everything;
- ``--cull-unobserved``: the ground-truth mesh is subdivided until no edge is longer than half the
  cull distance, and a face is kept only if its centroid lies within ``--cull-distance-m``
  (default: one map voxel) of an *observed* point: the centre of a voxel of the run's saved map
  (a voxel exists only where points were fused), moved into the ground-truth world. The surface
  inside an observed voxel is at most 0.87 voxel from its centre, so one voxel keeps all of it.

Outputs, next to the run: ``metrics.json`` (updated atomically; timing, loop and memory entries of
the run are kept) and ``plots/``: ``trajectories.png`` (top-down, with accepted loop edges from
``loops.csv``), ``translation_error.png``, ``mesh_error_histogram.png`` and ``mesh_error.ply``
(the mesh coloured by distance to ground truth, blue 0 to red >= 10 cm).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from frontends.errors import DatasetError
from frontends.frame import Intrinsics

logger = logging.getLogger("slam.eval")

PLOTS_DIR = "plots"
TUM_MAX_DT_S = 0.02
MESH_ERROR_MAX_M = 0.1
PLOT_SAMPLES = 50_000


class EvalError(ValueError):
    """A run folder or ground-truth file that cannot be evaluated (one-line message)."""


@dataclass
class RunTrajectories:
    """The poses a run wrote: ``timestamps`` (N,), ``odometry`` and ``slam`` (N, 4, 4)."""

    timestamps: np.ndarray
    odometry: np.ndarray
    slam: np.ndarray


@dataclass
class GroundTruth:
    """Ground truth of a run, each part optional, with where it came from."""

    poses: np.ndarray | None = None
    poses_from: str = ""
    mesh_path: Path | None = None
    intrinsics: Intrinsics | None = None
    sensor: str | None = None


def read_run_trajectories(run_dir: Path) -> RunTrajectories:
    """Both trajectories of a run folder (TUM files carry the timestamps)."""
    from slam.trajectory_io import read_kitti, read_tum

    run_dir = Path(run_dir)
    try:
        timestamps, slam = read_tum(run_dir / "poses_slam.tum.txt")
        _, odometry = read_tum(run_dir / "poses_odometry.tum.txt")
    except DatasetError:
        slam = read_kitti(run_dir / "poses_slam.kitti.txt")
        odometry = read_kitti(run_dir / "poses_odometry.kitti.txt")
        timestamps = np.arange(len(slam), dtype=np.float64)
    if len(odometry) != len(slam):
        raise EvalError(
            f"{run_dir}: poses_odometry has {len(odometry)} poses but poses_slam {len(slam)}; "
            "the run was interrupted, re-run it"
        )
    return RunTrajectories(timestamps, odometry, slam)


def read_gt_poses(path: Path, timestamps: np.ndarray, num_frames: int) -> np.ndarray:
    """Ground-truth poses for the run's frames from a KITTI (one per frame) or TUM file.

    TUM poses are associated with the run's timestamps (nearest within 20 ms); every frame needs
    one.
    """
    from slam.trajectory_io import read_kitti, read_tum

    path = Path(path)
    try:
        stamps, poses = read_tum(path)
    except DatasetError:
        poses = read_kitti(path)
        if len(poses) != num_frames:
            raise EvalError(
                f"{path}: {len(poses)} KITTI poses for a run of {num_frames} frames; pass the "
                "ground truth of exactly the frames the run used"
            ) from None
        return poses
    order = np.argsort(stamps)
    stamps, poses = stamps[order], poses[order]
    right = np.clip(np.searchsorted(stamps, timestamps), 1, len(stamps) - 1)
    left = right - 1
    nearest = np.where(
        np.abs(stamps[left] - timestamps) <= np.abs(stamps[right] - timestamps), left, right
    )
    nearest = np.where(len(stamps) == 1, 0, nearest)
    gap = np.abs(stamps[nearest] - timestamps)
    if np.any(gap > TUM_MAX_DT_S):
        first = int(np.argmax(gap > TUM_MAX_DT_S))
        raise EvalError(
            f"{path}: no ground-truth pose within {TUM_MAX_DT_S * 1e3:.0f} ms of frame {first} "
            f"(t = {timestamps[first]:.6f}); pass the ground truth of this sequence"
        )
    return poses[nearest]


def _load_run_config(run_dir: Path):
    from slam.config import load_run_config

    path = Path(run_dir) / "config.yaml"
    return load_run_config(path) if path.is_file() else None


def _source_ground_truth(cfg) -> GroundTruth:
    """Rebuild the run's source from its config (generated data may be regenerated)."""
    from slam.builders import build_source

    source = build_source(cfg)
    intrinsics = source[0].intrinsics if len(source) else None
    return GroundTruth(
        poses=source.gt_poses,
        poses_from=f"source {cfg.source.dataset} ({source.name})",
        mesh_path=source.gt_mesh_path,
        intrinsics=intrinsics,
        sensor=source.sensor,
    )


def find_ground_truth(
    run_dir: Path,
    trajectories: RunTrajectories,
    run_metrics: dict[str, Any],
    cfg,
    *,
    gt_poses_path: Path | None = None,
    gt_mesh_path: Path | None = None,
) -> GroundTruth:
    """Locate the ground truth of a run (order in the module docstring)."""
    run_dir = Path(run_dir)
    n = len(trajectories.slam)
    gt = GroundTruth(sensor=run_metrics.get("sensor"))
    if gt_poses_path is not None:
        gt.poses = read_gt_poses(gt_poses_path, trajectories.timestamps, n)
        gt.poses_from = str(gt_poses_path)
    else:
        for name in ("poses_gt.tum.txt", "poses_gt.kitti.txt"):
            if (run_dir / name).is_file():
                gt.poses = read_gt_poses(run_dir / name, trajectories.timestamps, n)
                gt.poses_from = str(run_dir / name)
                break
    recorded_mesh = (run_metrics.get("mesh") or {}).get("gt_mesh")
    if gt_mesh_path is not None:
        gt.mesh_path = Path(gt_mesh_path)
    elif recorded_mesh and Path(recorded_mesh).is_file():
        gt.mesh_path = Path(recorded_mesh)
    needs_source = gt.poses is None or gt.mesh_path is None or gt.sensor == "rgbd"
    if needs_source and cfg is not None:
        try:
            from_source = _source_ground_truth(cfg)
        except (DatasetError, FileNotFoundError, OSError) as exc:
            logger.warning("could not rebuild the run's source for ground truth: %s", exc)
        else:
            if gt.poses is None and from_source.poses is not None:
                if len(from_source.poses) != n:
                    logger.warning(
                        "source has %d ground-truth poses for %d run frames; ignored",
                        len(from_source.poses),
                        n,
                    )
                else:
                    gt.poses, gt.poses_from = from_source.poses, from_source.poses_from
            gt.mesh_path = gt.mesh_path or from_source.mesh_path
            gt.intrinsics = from_source.intrinsics
            gt.sensor = gt.sensor or from_source.sensor
    return gt


def trajectory_section(trajectories: RunTrajectories, gt_poses: np.ndarray) -> dict[str, Any]:
    """``metrics.json["trajectory"]``: the same numbers ``slam.run_metrics`` writes."""
    from slam.metrics.trajectory import kitti_lengths_within, trajectory_metrics

    lengths = kitti_lengths_within(gt_poses)
    return {
        "odometry": trajectory_metrics(
            trajectories.odometry, gt_poses, kitti_lengths_m=lengths
        ).as_dict(),
        "slam": trajectory_metrics(trajectories.slam, gt_poses, kitti_lengths_m=lengths).as_dict(),
    }


def observed_face_mask(
    gt_mesh: trimesh.Trimesh, observed_points: np.ndarray, distance_m: float
) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Subdivide ``gt_mesh`` (edges <= distance / 2) and mark faces whose centroid lies within
    ``distance_m`` of an observed point. Returns ``(subdivided mesh, mask)``."""
    from scipy.spatial import cKDTree

    vertices, faces = trimesh.remesh.subdivide_to_size(
        gt_mesh.vertices, gt_mesh.faces, max_edge=distance_m / 2.0, max_iter=12
    )
    fine = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    if len(observed_points) == 0:
        return fine, np.zeros(len(fine.faces), dtype=bool)
    distance, _ = cKDTree(observed_points).query(
        fine.triangles_center, distance_upper_bound=distance_m, workers=-1
    )
    return fine, np.isfinite(distance)


def load_map_voxels(run_dir: Path) -> tuple[np.ndarray, float, dict[int, np.ndarray]]:
    """Voxel centres (world W), voxel size and current anchor poses ``T_W_A`` by submap id of the
    run's saved map."""
    from mapping.neural_map import NeuralMap

    candidates = sorted(Path(run_dir).glob("map.*"))
    if not candidates:
        raise EvalError(f"{run_dir}: no map file (map.npz); the run was made with write_map off")
    neural_map, submaps = NeuralMap.load(candidates[0])
    centers, weights = neural_map.voxel_centers()
    anchors = {s.submap_id: np.asarray(s.T_W_A) for s in submaps}
    return np.asarray(centers)[np.asarray(weights) > 0], neural_map.voxel_size_m, anchors


def mesh_section(
    run_dir: Path,
    mesh: trimesh.Trimesh,
    gt: GroundTruth,
    T_gt_W: np.ndarray,
    num_samples: int,
    *,
    cull_unobserved: bool,
    cull_distance_m: float | None,
    lidar_range_m: float | None = None,
) -> tuple[dict[str, Any], trimesh.Trimesh, np.ndarray | None]:
    """``metrics.json["mesh"]`` plus the ground-truth mesh and face mask used for completion."""
    from slam.metrics.mesh import mesh_metrics
    from slam.run_metrics import mesh_errors

    gt_mesh = trimesh.load(gt.mesh_path, force="mesh", process=False)
    if not cull_unobserved:
        # The same culling as the run itself (slam.run_metrics.collect_metrics).
        from slam.metrics.mesh import visible_face_mask
        from slam.run_metrics import near_trajectory_mask

        cameras = None
        if gt.intrinsics is not None:
            cameras = (gt.intrinsics.K, gt.intrinsics.width, gt.intrinsics.height)
        range_m = None if cameras is not None else lidar_range_m
        section = mesh_errors(
            mesh, gt.mesh_path, T_gt_W, num_samples, gt.poses, cameras, lidar_range_m=range_m
        )
        mask = None
        if section["completion_seen_only"]:
            if cameras is not None:
                poses = gt.poses[:: max(1, len(gt.poses) // 200)]
                mask = visible_face_mask(gt_mesh, poses, *cameras)
                section["culling"] = "frustum"
            else:
                mask = near_trajectory_mask(gt_mesh, gt.poses[:, :3, 3], range_m)
                section["culling"] = f"within {range_m} m of the trajectory"
        else:
            section["culling"] = "none"
        return section, gt_mesh, mask

    centers_W, voxel_size_m, _ = load_map_voxels(run_dir)
    distance_m = cull_distance_m if cull_distance_m is not None else voxel_size_m
    centers_gt = centers_W @ T_gt_W[:3, :3].T + T_gt_W[:3, 3]
    fine, mask = observed_face_mask(gt_mesh, centers_gt, distance_m)
    if not mask.any():
        raise EvalError(
            f"{run_dir}: no ground-truth face lies within {distance_m} m of the map; the run's "
            "frame does not match the ground truth, or pass a larger --cull-distance-m"
        )
    pred = mesh.copy()
    pred.apply_transform(T_gt_W)
    section = mesh_metrics(pred, fine, num_samples=num_samples, gt_face_mask=mask).as_dict()
    section.update(
        gt_mesh=str(gt.mesh_path),
        completion_visible_only=True,
        culling="observed",
        cull_distance_m=distance_m,
        observed_gt_area_fraction=float(fine.area_faces[mask].sum() / fine.area),
    )
    return section, fine, mask


def loop_edges(run_dir: Path, anchors_W: dict[int, np.ndarray]) -> np.ndarray:
    """Accepted loop edges kept by the pose graph, from ``loops.csv``, as (M, 2, 3) positions."""
    path = Path(run_dir) / "loops.csv"
    if not path.is_file():
        return np.zeros((0, 2, 3))
    edges = []
    with path.open(newline="") as stream:
        for row in csv.DictReader(stream):
            if row.get("status") != "accepted" or row.get("graph_inlier") == "false":
                continue
            reference, query = int(row["reference_submap"]), int(row["query_submap"])
            if reference in anchors_W and query in anchors_W:
                edges.append([anchors_W[reference][:3, 3], anchors_W[query][:3, 3]])
    return np.asarray(edges, dtype=np.float64).reshape(-1, 2, 3)


def _aligned(poses: np.ndarray, gt: np.ndarray) -> np.ndarray:
    from slam.metrics.trajectory import align_se3

    return align_se3(poses, gt) @ poses


def draw_plots(
    run_dir: Path,
    trajectories: RunTrajectories,
    gt: GroundTruth,
    *,
    mesh: trimesh.Trimesh | None,
    gt_mesh: trimesh.Trimesh | None,
    gt_face_mask: np.ndarray | None,
    T_gt_W: np.ndarray,
    threshold_m: float,
) -> list[Path]:
    """All plots of a run into ``RUN_DIR/plots``."""
    from slam import plots
    from slam.metrics.mesh import surface_distances

    out = Path(run_dir) / PLOTS_DIR
    written: list[Path] = []
    try:
        _, _, anchors = load_map_voxels(run_dir)
    except (EvalError, ValueError, OSError) as exc:
        logger.warning("loop edges not drawn: %s", exc)
        anchors = {}
    edges_W = loop_edges(run_dir, anchors)
    if gt.poses is not None:
        named = {
            "gt": gt.poses,
            "odometry": _aligned(trajectories.odometry, gt.poses),
            "slam": T_gt_W @ trajectories.slam,
        }
        edges = edges_W @ T_gt_W[:3, :3].T + T_gt_W[:3, 3] if len(edges_W) else edges_W
    else:
        named = {"odometry": trajectories.odometry, "slam": trajectories.slam}
        edges = edges_W
    title = f"{Path(run_dir).name}: trajectories (top-down)"
    written.append(
        plots.plot_trajectories_top_down(
            out / "trajectories.png", named, loop_edges=edges, title=title
        )
    )
    if gt.poses is not None:
        times = trajectories.timestamps - trajectories.timestamps[0]
        errors = {
            name: np.linalg.norm(named[name][:, :3, 3] - gt.poses[:, :3, 3], axis=1)
            for name in ("odometry", "slam")
        }
        written.append(plots.plot_translation_error(out / "translation_error.png", times, errors))
    if mesh is not None and gt_mesh is not None and len(mesh.faces):
        pred = mesh.copy()
        pred.apply_transform(T_gt_W)
        samples = trimesh.sample.sample_surface(pred, PLOT_SAMPLES, seed=0)[0]
        weights = None if gt_face_mask is None else gt_mesh.area_faces * gt_face_mask
        gt_samples = trimesh.sample.sample_surface(
            gt_mesh, PLOT_SAMPLES, face_weight=weights, seed=1
        )[0]
        distances = {
            "accuracy (mesh -> GT)": surface_distances(samples, gt_mesh),
            "completion (GT -> mesh)": surface_distances(gt_samples, pred),
        }
        written.append(
            plots.plot_error_histogram(
                out / "mesh_error_histogram.png", distances, threshold_m=threshold_m
            )
        )
        vertex_distances = surface_distances(pred.vertices, gt_mesh)
        written.append(
            plots.write_error_colored_mesh(
                out / "mesh_error.ply", pred, vertex_distances, max_m=MESH_ERROR_MAX_M
            )
        )
    return written


def evaluate_run(
    run_dir: Path,
    *,
    gt_poses_path: Path | None = None,
    gt_mesh_path: Path | None = None,
    cull_unobserved: bool = False,
    cull_distance_m: float | None = None,
    num_samples: int | None = None,
    make_plots: bool = True,
    write: bool = True,
) -> dict[str, Any]:
    """Recompute the metrics of ``run_dir`` (see the module docstring); returns ``metrics.json``'s
    new content and, with ``write``, writes it."""
    from slam.metrics.trajectory import align_se3
    from slam.outputs import RunOutputs

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise EvalError(f"{run_dir}: run folder not found; pass the folder a run wrote")
    metrics_path = run_dir / "metrics.json"
    run_metrics: dict[str, Any] = {}
    if metrics_path.is_file():
        try:
            run_metrics = json.loads(metrics_path.read_text())
        except json.JSONDecodeError:
            raise EvalError(f"{metrics_path}: not valid JSON; delete it and re-evaluate") from None
    cfg = _load_run_config(run_dir)
    trajectories = read_run_trajectories(run_dir)
    gt = find_ground_truth(
        run_dir,
        trajectories,
        run_metrics,
        cfg,
        gt_poses_path=gt_poses_path,
        gt_mesh_path=gt_mesh_path,
    )
    metrics = dict(run_metrics)
    T_gt_W = np.eye(4)
    if gt.poses is not None and len(gt.poses) >= 2:
        metrics["trajectory"] = trajectory_section(trajectories, gt.poses)
        T_gt_W = align_se3(trajectories.slam, gt.poses)
    else:
        logger.warning("%s: no ground-truth poses; trajectory metrics skipped", run_dir)

    mesh = None
    mesh_file = run_dir / "mesh.ply"
    if mesh_file.is_file():
        mesh = trimesh.load(mesh_file, force="mesh", process=False)
    gt_mesh, mask = None, None
    if mesh is not None and gt.mesh_path is not None and gt.poses is not None:
        if num_samples is None:
            num_samples = cfg.output.mesh_samples if cfg is not None else 200_000
        try:
            metrics["mesh"], gt_mesh, mask = mesh_section(
                run_dir,
                mesh,
                gt,
                T_gt_W,
                num_samples,
                cull_unobserved=cull_unobserved,
                cull_distance_m=cull_distance_m,
                lidar_range_m=(
                    cfg.submaps.max_range_m if cfg is not None and gt.sensor == "lidar" else None
                ),
            )
        except ValueError as exc:
            logger.warning("mesh metrics skipped: %s", exc)
    elif mesh is not None:
        logger.warning("%s: no ground-truth mesh or poses; mesh metrics skipped", run_dir)

    plot_files: list[Path] = []
    if make_plots:
        threshold = float((metrics.get("mesh") or {}).get("threshold_m") or 0.05)
        plot_files = draw_plots(
            run_dir,
            trajectories,
            gt,
            mesh=mesh,
            gt_mesh=gt_mesh,
            gt_face_mask=mask,
            T_gt_W=T_gt_W,
            threshold_m=threshold,
        )
    metrics["evaluation"] = {
        "gt_poses": gt.poses_from or None,
        "gt_mesh": str(gt.mesh_path) if gt.mesh_path else None,
        "culling": (metrics.get("mesh") or {}).get("culling"),
        "plots": [str(p.relative_to(run_dir)) for p in plot_files],
    }
    if write:
        RunOutputs(run_dir).write_metrics(metrics)
    return metrics


def summary_lines(metrics: dict[str, Any]) -> list[str]:
    """A few lines for the terminal."""

    def finite(value: float | None) -> bool:
        return value is not None and math.isfinite(value)

    def cm(value: float | None) -> str:
        return f"{100 * value:.2f} cm" if finite(value) else "n/a"

    lines = []
    trajectory = metrics.get("trajectory")
    if trajectory:
        for name in ("odometry", "slam"):
            t = trajectory[name]
            kitti = t["kitti_t_err_percent"]
            lines.append(
                f"{name:8s} ATE {cm(t['ate_rmse_m'])}, RPE {cm(t['rpe_trans_rmse_m'])}/frame, "
                f"KITTI t_err {f'{kitti:.2f} %' if finite(kitti) else 'n/a'}"
            )
    mesh = metrics.get("mesh")
    if mesh:
        lines.append(
            f"mesh     accuracy {cm(mesh['accuracy_m'])}, completion {cm(mesh['completion_m'])}, "
            f"ratio {100 * (mesh['completion_ratio'] or 0):.1f}% (culling {mesh.get('culling')})"
        )
    for plot in (metrics.get("evaluation") or {}).get("plots", []):
        lines.append(f"plot     {plot}")
    return lines


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m slam.eval",
        description="Recompute the metrics of a finished run and draw its plots "
        "(or: python -m slam.eval transform --help).",
    )
    parser.add_argument("run_dir", type=Path, help="run folder written by python -m slam.run")
    parser.add_argument("--gt-poses", type=Path, help="ground-truth trajectory (KITTI or TUM)")
    parser.add_argument("--gt-mesh", type=Path, help="ground-truth mesh (PLY/OBJ, GT world frame)")
    parser.add_argument(
        "--cull-unobserved",
        action="store_true",
        help="completion only over ground truth within --cull-distance-m of the map's voxels",
    )
    parser.add_argument(
        "--cull-distance-m", type=float, help="culling distance (default: one map voxel)"
    )
    parser.add_argument("--samples", type=int, help="surface samples per mesh (default: config)")
    parser.add_argument("--no-plots", action="store_true", help="metrics only")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "transform":
        from slam.transform_experiment import main as transform_main

        return transform_main(argv[1:])
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        metrics = evaluate_run(
            args.run_dir,
            gt_poses_path=args.gt_poses,
            gt_mesh_path=args.gt_mesh,
            cull_unobserved=args.cull_unobserved,
            cull_distance_m=args.cull_distance_m,
            num_samples=args.samples,
            make_plots=not args.no_plots,
        )
    except (EvalError, DatasetError, FileNotFoundError, ValueError) as exc:
        if args.debug:
            raise
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1
    for line in summary_lines(metrics):
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
