"""``python -m slam.eval RUN_DIR``: recompute the metrics of a finished run and draw its plots.

    python -m slam.eval RUN_DIR [--gt-poses FILE] [--gt-mesh FILE] [--culling observed|view]
    python -m slam.eval RUN_DIR --figures DIR     # also the README pictures (PNG) into DIR
    python -m slam.eval transform --dataset demo [--root DIR] [--frames A:B:STEP]   (see
        slam/transform_experiment.py)

What is recomputed, with the same functions the run used (``slam.evaluation.metrics``,
``slam.evaluation.run_metrics``):

- trajectory, for ``odometry`` and ``slam`` (loop-closed): ATE RMSE after SE(3) Umeyama alignment,
  RPE (consecutive frames), KITTI relative error, over the frames that have a ground-truth pose;
- mesh (``mesh.ply``, moved into the ground-truth world by the SLAM trajectory's alignment):
  accuracy, completion and completion ratio (< 5 cm).

Trajectory files are in the dataset's own frame (for ICL-NUIM the loader's mirrored world is
mirrored back when writing them); they are compared with ground truth in that frame.

Where the ground truth comes from, first match wins:

- poses: ``--gt-poses`` (KITTI or TUM file; TUM is associated by timestamp), then
  ``poses_gt.{kitti,tum}.txt`` in the run folder, then the run's source rebuilt from its
  ``config.yaml`` (``Source.gt_poses`` of the same frames);
- mesh: ``--gt-mesh``, then ``mesh.gt_mesh`` of the run's ``metrics.json``, then the source's
  ``gt_mesh_path``.

Culling of ground truth the run never saw (completion only; accuracy always uses the whole
surface), as the run does (``slam.evaluation.run_metrics``):

- ``observed`` (default): the ground-truth mesh is subdivided until no edge is longer than
  the cull distance, and a face is kept only if its centroid lies within ``--cull-distance-m``
  (default: one map voxel) of the centre of a voxel of the run's saved map (a voxel exists only
  where points were fused), moved into the ground-truth world; ``mesh_unculled`` holds the
  looser ``view`` numbers;
- ``view``: RGB-D runs keep the faces in the view frustum of a ground-truth camera, LiDAR runs
  the faces within the submap range of the trajectory.

Outputs, next to the run: ``metrics.json`` (updated atomically; timing, loop and memory entries of
the run are kept) and ``plots/``: ``trajectories.png`` (top-down, with accepted loop edges from
``loops.csv``), ``translation_error.png``, ``mesh_error_histogram.png`` and ``mesh_error.ply``
(the mesh coloured by distance to ground truth, blue 0 to red >= 10 cm). ``--figures DIR`` adds
small PNGs for documentation (``slam.figures``): the top-down trajectories with loop edges, the
mesh coloured by its error and a shaded snapshot of the mesh, rendered offscreen.
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
from slam.evaluation.run_metrics import observed_face_mask

__all__ = ["EvalError", "evaluate_run", "observed_face_mask", "read_gt_poses"]

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
    from slam.app.trajectory_io import read_kitti, read_tum

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

    TUM poses are associated with the run's timestamps (nearest within 20 ms); frames without one
    get a row of NaN (they are not scored), and at least two frames need one.
    """
    from slam.app.trajectory_io import read_kitti, read_tum

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
    missing = gap > TUM_MAX_DT_S
    if np.count_nonzero(~missing) < 2:
        first = int(np.argmax(missing))
        raise EvalError(
            f"{path}: no ground-truth pose within {TUM_MAX_DT_S * 1e3:.0f} ms of frame {first} "
            f"(t = {timestamps[first]:.6f}); pass the ground truth of this sequence"
        )
    if missing.any():
        logger.warning("%s: %d frames have no ground-truth pose; not scored", path, missing.sum())
    out = poses[nearest].copy()
    out[missing] = np.nan
    return out


def _load_run_config(run_dir: Path):
    from slam.app.config import load_run_config

    path = Path(run_dir) / "config.yaml"
    return load_run_config(path) if path.is_file() else None


def _to_loader_frame(cfg, poses: np.ndarray) -> np.ndarray:
    """Poses in the dataset's frame (as files hold them) -> the loader's frame (mesh, map, source
    ground truth). The conversion is a reflection ``M T M``, its own inverse."""
    if cfg is None:
        return poses
    from frontends.sources.base import source_class

    try:
        cls = source_class(cfg.source.dataset)
    except DatasetError:
        return poses
    return cls.to_dataset_frame(poses)


def _source_ground_truth(cfg) -> GroundTruth:
    """Rebuild the run's source from its config (generated data may be regenerated)."""
    from slam.app.builders import build_source

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
    if gt.poses is not None:
        gt.poses = _to_loader_frame(cfg, gt.poses)
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
    """``metrics.json["trajectory"]``: the same numbers ``slam.evaluation.run_metrics`` writes."""
    from slam.evaluation.run_metrics import trajectory_section as section

    result = section(trajectories.odometry, trajectories.slam, gt_poses)
    if result is None:
        raise EvalError("fewer than two frames have a ground-truth pose; nothing to score")
    return result


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
    culling: str,
    cull_distance_m: float | None,
    lidar_range_m: float | None = None,
) -> dict[str, Any]:
    """``metrics.json``'s ``mesh`` (and ``mesh_unculled``) sections, computed as the run does
    (:func:`slam.evaluation.run_metrics.mesh_sections`); private ``_gt``/``_mask`` entries for
    plotting."""
    from slam.evaluation.run_metrics import mesh_sections

    cameras = None
    if gt.intrinsics is not None:
        cameras = (gt.intrinsics.K, gt.intrinsics.width, gt.intrinsics.height)
    from slam.evaluation.run_metrics import cull_distance

    observed, distance_m = None, cull_distance_m or 0.0
    if culling == "observed" and cameras is not None:
        distance_m = cull_distance_m if cull_distance_m is not None else cull_distance(True, 0.0)
    elif culling == "observed":
        try:
            observed, voxel_size_m, _ = load_map_voxels(run_dir)
        except EvalError as exc:
            logger.warning("%s; completion over surfaces in range instead", exc)
        else:
            distance_m = cull_distance_m if cull_distance_m is not None else voxel_size_m

    scored = np.isfinite(gt.poses).all(axis=(1, 2))
    sections = mesh_sections(
        mesh,
        gt.mesh_path,
        T_gt_W,
        num_samples,
        gt.poses[scored],
        observed_points_W=observed,
        cull_distance_m=distance_m,
        cameras=cameras,
        lidar_range_m=None if cameras is not None else lidar_range_m,
        observe=culling == "observed",
    )
    if culling == "observed" and "mesh_unculled" not in sections:
        raise EvalError(
            f"{run_dir}: no ground-truth face lies within {distance_m} m of the map; the run's "
            "frame does not match the ground truth, or pass a larger --cull-distance-m"
        )
    return sections


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
    from slam.evaluation.metrics.trajectory import align_se3

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
    figures_dir: Path | None = None,
) -> list[Path]:
    """All plots of a run into ``RUN_DIR/plots`` (and the documentation figures into
    ``figures_dir``)."""
    from slam.evaluation import plots
    from slam.evaluation.metrics.mesh import surface_distances

    out = Path(run_dir) / PLOTS_DIR
    written: list[Path] = []
    try:
        _, _, anchors = load_map_voxels(run_dir)
    except (EvalError, ValueError, OSError) as exc:
        logger.warning("loop edges not drawn: %s", exc)
        anchors = {}
    edges_W = loop_edges(run_dir, anchors)
    scored = None if gt.poses is None else np.isfinite(gt.poses).all(axis=(1, 2))
    if gt.poses is not None:
        named = {
            "gt": gt.poses[scored],
            "odometry": _aligned(trajectories.odometry[scored], gt.poses[scored]),
            "slam": T_gt_W @ trajectories.slam[scored],
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
        times = (trajectories.timestamps - trajectories.timestamps[0])[scored]
        errors = {
            name: np.linalg.norm(named[name][:, :3, 3] - named["gt"][:, :3, 3], axis=1)
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
    if figures_dir is not None:
        figure_mesh, distances_m = None, None
        if mesh is not None and len(mesh.faces):
            figure_mesh = mesh.copy()
            if gt.poses is not None:
                figure_mesh.apply_transform(T_gt_W)
            if gt_mesh is not None:
                distances_m = surface_distances(figure_mesh.vertices, gt_mesh)
        written += write_figures(
            Path(figures_dir),
            named,
            edges,
            figure_mesh,
            distances_m,
            sensor=gt.sensor or "lidar",
            name=Path(run_dir).name,
        )
    return written


def up_axis_of(poses: np.ndarray, sensor: str) -> str:
    """The signed world axis closest to "up": the mean sensor z axis for LiDAR, minus the mean
    camera y axis for RGB-D (images have y down)."""
    poses = np.asarray(poses)
    up = poses[:, :3, 2].mean(axis=0) if sensor == "lidar" else -poses[:, :3, 1].mean(axis=0)
    axis = int(np.argmax(np.abs(up)))
    return ("+" if up[axis] >= 0 else "-") + "xyz"[axis]


def write_figures(
    out: Path,
    trajectories: dict[str, np.ndarray],
    loop_edges_gt: np.ndarray,
    mesh: trimesh.Trimesh | None,
    vertex_distances_m: np.ndarray | None,
    *,
    sensor: str,
    name: str,
) -> list[Path]:
    """Small PNGs for documentation: ``trajectory.png`` (top-down, loop edges), ``mesh.png``
    (shaded snapshot) and ``mesh_error.png`` (mesh coloured by distance to ground truth)."""
    from slam.evaluation import plots

    written = [
        plots.plot_trajectories_top_down(
            out / "trajectory.png",
            trajectories,
            loop_edges=loop_edges_gt,
            title=f"{name}: trajectories and loop closures",
            size_in=(5.0, 4.2),
            dpi=100,
        )
    ]
    if mesh is None:
        return written
    up = up_axis_of(trajectories.get("slam", next(iter(trajectories.values()))), sensor)
    written.append(plots.render_mesh(out / "mesh.png", mesh, up_axis=up, title=f"{name}: mesh"))
    if vertex_distances_m is not None:
        vertex_colors = plots.distance_colors(vertex_distances_m, MESH_ERROR_MAX_M)
        face_colors = vertex_colors[np.asarray(mesh.faces)].mean(axis=1).astype(np.uint8)
        written.append(
            plots.render_mesh(
                out / "mesh_error.png",
                mesh,
                face_colors=face_colors,
                up_axis=up,
                title=f"{name}: distance to ground truth",
                colorbar=("m", MESH_ERROR_MAX_M),
            )
        )
    return written


def evaluate_run(
    run_dir: Path,
    *,
    gt_poses_path: Path | None = None,
    gt_mesh_path: Path | None = None,
    culling: str = "observed",
    cull_distance_m: float | None = None,
    num_samples: int | None = None,
    make_plots: bool = True,
    figures_dir: Path | None = None,
    write: bool = True,
) -> dict[str, Any]:
    """Recompute the metrics of ``run_dir`` (see the module docstring); returns ``metrics.json``'s
    new content and, with ``write``, writes it. ``figures_dir``: also write the documentation
    figures there (:mod:`slam.figures`)."""
    from slam.app.outputs import RunOutputs
    from slam.evaluation.metrics.trajectory import align_se3
    from slam.evaluation.run_metrics import public

    if culling not in ("observed", "view"):
        raise EvalError(f"culling '{culling}': choose 'observed' or 'view'")
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
    trajectories.odometry = _to_loader_frame(cfg, trajectories.odometry)
    trajectories.slam = _to_loader_frame(cfg, trajectories.slam)
    gt = find_ground_truth(
        run_dir,
        trajectories,
        run_metrics,
        cfg,
        gt_poses_path=gt_poses_path,
        gt_mesh_path=gt_mesh_path,
    )
    metrics = dict(run_metrics)
    for stale in ("trajectory", "mesh", "mesh_unculled"):
        metrics.pop(stale, None)
    T_gt_W = np.eye(4)
    if gt.poses is not None and np.isfinite(gt.poses).all(axis=(1, 2)).sum() >= 2:
        metrics["trajectory"] = trajectory_section(trajectories, gt.poses)
        scored = np.isfinite(gt.poses).all(axis=(1, 2))
        T_gt_W = align_se3(trajectories.slam[scored], gt.poses[scored])
    else:
        gt.poses = None
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
            sections = mesh_section(
                run_dir,
                mesh,
                gt,
                T_gt_W,
                num_samples,
                culling=culling,
                cull_distance_m=cull_distance_m,
                lidar_range_m=(
                    cfg.submaps.max_range_m if cfg is not None and gt.sensor == "lidar" else None
                ),
            )
        except ValueError as exc:
            logger.warning("mesh metrics skipped: %s", exc)
        else:
            gt_mesh, mask = sections["mesh"]["_gt"], sections["mesh"]["_mask"]
            metrics.update({name: public(value) for name, value in sections.items()})
    elif mesh is not None:
        logger.warning("%s: no ground-truth mesh or poses; mesh metrics skipped", run_dir)

    plot_files: list[Path] = []
    if make_plots or figures_dir is not None:
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
            figures_dir=figures_dir,
        )
    metrics["evaluation"] = {
        "gt_poses": gt.poses_from or None,
        "gt_mesh": str(gt.mesh_path) if gt.mesh_path else None,
        "culling": (metrics.get("mesh") or {}).get("culling"),
        "plots": [_relative(p, run_dir) for p in plot_files],
    }
    if write:
        RunOutputs(run_dir).write_metrics(metrics)
    return metrics


def _relative(path: Path, run_dir: Path) -> str:
    try:
        return str(Path(path).relative_to(run_dir))
    except ValueError:
        return str(path)


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
            axes = ""
            if "ate_z_rmse_m" in t:  # metrics.json written before the per-axis split lacks it
                axes = " (x/y/z " + "/".join(cm(t[f"ate_{a}_rmse_m"]) for a in "xyz") + ")"
            lines.append(
                f"{name:8s} ATE {cm(t['ate_rmse_m'])}{axes}, "
                f"RPE {cm(t['rpe_trans_rmse_m'])}/frame, "
                f"KITTI t_err {f'{kitti:.2f} %' if finite(kitti) else 'n/a'}"
            )
    mesh = metrics.get("mesh")
    if mesh:
        lines.append(
            f"mesh     accuracy {cm(mesh['accuracy_m'])}, completion {cm(mesh['completion_m'])}, "
            f"ratio {100 * (mesh['completion_ratio'] or 0):.1f}% (culling {mesh.get('culling')})"
        )
    unculled = metrics.get("mesh_unculled")
    if unculled:
        ratio = 100 * (unculled["completion_ratio"] or 0)
        lines.append(
            f"         unculled ({unculled.get('culling')}): completion "
            f"{cm(unculled['completion_m'])}, ratio {ratio:.1f}%"
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
        "--culling",
        choices=["observed", "view"],
        default="observed",
        help="completion over ground truth within --cull-distance-m of the map's voxels "
        "(observed, as the run) or over everything in view / LiDAR range",
    )
    parser.add_argument(
        "--figures",
        type=Path,
        metavar="DIR",
        help="also write small documentation PNGs (trajectories with loops, mesh coloured by "
        "error, mesh snapshot) into DIR",
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
        from slam.evaluation.transform_experiment import main as transform_main

        return transform_main(argv[1:])
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        metrics = evaluate_run(
            args.run_dir,
            gt_poses_path=args.gt_poses,
            gt_mesh_path=args.gt_mesh,
            culling=args.culling,
            cull_distance_m=args.cull_distance_m,
            num_samples=args.samples,
            make_plots=not args.no_plots,
            figures_dir=args.figures,
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
