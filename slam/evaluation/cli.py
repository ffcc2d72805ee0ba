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

A merged run (``slam.merge``, ``slam.run --map``: it has ``sessions.csv``) is read as a run
without odometry of its own: what exists is scored, and what was skipped is listed (in the
summary and ``metrics.json``'s ``evaluation.skipped``), as for any run without ground truth.

Outputs, next to the run: ``metrics.json`` (updated atomically; timing, loop and memory entries of
the run are kept) and ``plots/``: ``trajectories.png`` (top-down, with accepted loop edges from
``loops.csv``), ``translation_error.png``, ``mesh_error_histogram.png`` and ``mesh_error.ply``
(the mesh coloured by distance to ground truth, blue 0 to red >= 10 cm). ``--figures DIR`` adds
small PNGs for documentation (``slam.figures``): the top-down trajectories with loop edges, the
mesh coloured by its error and a shaded snapshot of the mesh, rendered offscreen.
"""

from __future__ import annotations

import argparse
import errno
import json
import logging
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from common.atomic_io import write_problem
from frontends.errors import DatasetError
from slam.assembly.config import OneLineParser, UsageError
from slam.assembly.error_line import error_line
from slam.evaluation.run_metrics import (
    CullDistanceTooSmall,
    observed_face_mask,
    trajectory_section,
)
from slam.evaluation.run_plots import draw_plots
from slam.evaluation.summary import length, mesh_lines
from slam.run_folder.reader import (
    EvalError,
    GroundTruth,
    _load_run_config,
    _to_loader_frame,
    check_run_finished,
    find_ground_truth,
    load_map_voxels,
    read_gt_poses,
    read_run_trajectories,
)

__all__ = ["EvalError", "evaluate_run", "observed_face_mask", "read_gt_poses"]

logger = logging.getLogger("slam.eval")


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
    from slam.evaluation.run_metrics import cull_distance, mesh_sections

    observed, distance_m = None, cull_distance_m or 0.0
    if culling == "observed" and gt.intrinsics is not None:
        distance_m = cull_distance_m if cull_distance_m is not None else cull_distance(True, 0.0)
    elif culling == "observed":
        try:
            observed, voxel_size_m, _ = load_map_voxels(run_dir)
        except EvalError as exc:
            logger.warning("%s; completion over surfaces in range instead", exc)
        else:
            distance_m = cull_distance_m if cull_distance_m is not None else voxel_size_m

    scored = np.isfinite(gt.poses).all(axis=(1, 2))
    try:
        sections = mesh_sections(
            mesh,
            gt.mesh_path,
            T_gt_W,
            num_samples,
            gt.poses[scored],
            observed_points_W=observed,
            cull_distance_m=distance_m,
            intrinsics=gt.intrinsics,
            lidar_range_m=lidar_range_m,
            observe=culling == "observed",
        )
    except CullDistanceTooSmall as exc:
        raise EvalError(f"--cull-distance-m: {exc}") from None
    if culling == "observed" and "mesh_unculled" not in sections:
        raise EvalError(
            f"{run_dir}: no ground-truth face lies within {distance_m} m of the map; the run's "
            "frame does not match the ground truth, or pass a larger --cull-distance-m"
        )
    return sections


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
    from slam.evaluation.metrics.trajectory import align_se3
    from slam.evaluation.run_metrics import public
    from slam.run_folder.outputs import RunOutputs

    if culling not in ("observed", "view"):
        raise EvalError(f"culling '{culling}': choose 'observed' or 'view'")
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise EvalError(f"{run_dir}: run folder not found; pass the folder a run wrote")
    check_run_finished(run_dir)
    if write or make_plots:
        _require_writable(run_dir, f"{run_dir}: cannot write in the run folder")
    if figures_dir is not None:
        _require_writable(Path(figures_dir), f"--figures {figures_dir}: cannot write there")
    metrics_path = run_dir / "metrics.json"
    run_metrics: dict[str, Any] = {}
    if metrics_path.is_file():
        try:
            run_metrics = json.loads(metrics_path.read_text())
        except json.JSONDecodeError:
            raise EvalError(f"{metrics_path}: not valid JSON; delete it and re-evaluate") from None
    cfg = _load_run_config(run_dir)
    trajectories = read_run_trajectories(run_dir)
    skipped = []
    if trajectories.odometry is None:
        skipped.append("odometry: a merged run has no odometry of its own")
    else:
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
    section = None  # the same numbers the run writes, over the frames with ground truth
    if gt.poses is not None:
        section = trajectory_section(trajectories.odometry, trajectories.slam, gt.poses, gt.sensor)
    if section is not None:
        metrics["trajectory"] = section
        scored = np.isfinite(gt.poses).all(axis=(1, 2))
        T_gt_W = align_se3(trajectories.slam[scored], gt.poses[scored])
    else:
        gt.poses = None
        skipped.append("trajectory metrics: no ground-truth poses")

    mesh = None
    mesh_file = run_dir / "mesh.ply"
    if mesh_file.is_file():
        mesh = read_mesh(mesh_file, "re-run to write the mesh again")
    if gt.mesh_path is not None and mesh is not None and gt.poses is not None:
        read_mesh(Path(gt.mesh_path), "pass a PLY/OBJ mesh with --gt-mesh")
    gt_mesh, mask = None, None
    if mesh is not None and gt.mesh_path is not None and gt.poses is not None:
        if num_samples is None:
            from slam.assembly.config import OutputConfig

            num_samples = cfg.output.mesh_samples if cfg is not None else 200_000
            # a run that did not score its mesh (0) is scored with the configuration's default
            num_samples = num_samples or OutputConfig.model_fields["mesh_samples"].default
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
        except EvalError:
            raise
        except ValueError as exc:
            skipped.append(f"mesh metrics: {' '.join(str(exc).split())}")
        else:
            gt_mesh, mask = sections["mesh"]["_gt"], sections["mesh"]["_mask"]
            metrics.update({name: public(value) for name, value in sections.items()})
    elif mesh is not None:
        missing = "ground-truth mesh" if gt.mesh_path is None else "ground-truth poses"
        skipped.append(f"mesh metrics: no {missing}")
    else:
        skipped.append("mesh metrics: no mesh.ply")

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
        "skipped": skipped,
    }
    if write:
        RunOutputs(run_dir).write_metrics(metrics)
    return metrics


def read_mesh(path: Path, fix: str) -> trimesh.Trimesh:
    """A mesh file with faces, else one :class:`EvalError` line naming it and ``fix`` (trimesh's
    readers raise anything from ``ValueError`` to ``struct.error`` on a corrupt file)."""
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise EvalError(f"{path}: not a readable mesh ({reason}); {fix}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise EvalError(f"{path}: holds no triangles; {fix}")
    return mesh


def _require_writable(folder: Path, what: str) -> None:
    """Refuse a folder the evaluation could not write into before computing anything."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        problem: str | None = exc.strerror or str(exc)
    else:
        problem = write_problem(folder)
    if problem is not None:
        raise EvalError(f"{what} ({problem}); copy the run folder to a writable disk")


_OS_HINTS = {
    errno.ENOSPC: "free some space",
    errno.EDQUOT: "free some space",
    errno.EROFS: "copy the run folder to a writable disk",
    errno.EACCES: "copy the run folder to a writable disk",
    errno.EPERM: "copy the run folder to a writable disk",
}


def _relative(path: Path, run_dir: Path) -> str:
    try:
        return str(Path(path).relative_to(run_dir))
    except ValueError:
        return str(path)


def summary_lines(metrics: dict[str, Any]) -> list[str]:
    """A few lines for the terminal: per-trajectory errors in more detail than a run prints."""
    lines = []
    trajectory = metrics.get("trajectory")
    if trajectory:
        for name in ("odometry", "slam"):
            if name not in trajectory:
                continue
            t = trajectory[name]
            kitti = t["kitti_t_err_percent"]
            axes = ""
            if "ate_z_rmse_m" in t:  # metrics.json written before the per-axis split lacks it
                axes = " (x/y/z " + "/".join(length(t[f"ate_{a}_rmse_m"]) for a in "xyz") + ")"
            kitti_text = "n/a" if kitti is None or not math.isfinite(kitti) else f"{kitti:.2f} %"
            lines.append(
                f"{name:8s} ATE {length(t['ate_rmse_m'])}{axes}, "
                f"RPE {length(t['rpe_trans_rmse_m'])}/frame, KITTI t_err {kitti_text}"
            )
            if "unaligned_rmse_m" in t:  # metrics.json written before the unaligned errors
                lines.append(
                    f"{'':8s} unaligned (first pose = identity, as the files): "
                    f"{length(t['unaligned_rmse_m'])}, yaw {t['unaligned_yaw_mean_abs_deg']:.2f} "
                    f"deg, tilt {t['unaligned_tilt_mean_deg']:.2f} deg (means)"
                )
    lines += mesh_lines(metrics)
    for plot in (metrics.get("evaluation") or {}).get("plots", []):
        lines.append(f"plot     {plot}")
    for reason in (metrics.get("evaluation") or {}).get("skipped", []):
        lines.append(f"skipped  {reason}")
    return lines


MAX_SAMPLES = 10_000_000
"""``--samples`` bound, as ``output.mesh_samples``'s (about 1 GB of distances per mesh)."""


def _samples(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number, e.g. 200000") from None
    if not 1000 <= value <= MAX_SAMPLES:
        raise argparse.ArgumentTypeError(f"{text}: pass 1000 to {MAX_SAMPLES:,} samples")
    return value


def _distance_m(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text}: pass a positive distance in metres")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
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
        "--cull-distance-m",
        type=_distance_m,
        help="culling distance in metres, positive (default: one map voxel); one that would "
        "subdivide the ground truth into more than 8 M faces is refused",
    )
    parser.add_argument(
        "--samples",
        type=_samples,
        help=f"surface samples per mesh, 1000 to {MAX_SAMPLES:,} (default: config)",
    )
    parser.add_argument("--no-plots", action="store_true", help="metrics only")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "transform":
        from slam.evaluation.transform_experiment import main as transform_main

        return transform_main(argv[1:])
    try:
        args = build_parser().parse_args(argv)
    except UsageError as exc:  # one line naming the option, exit status 2, as slam.run's
        print(f"error: {exc}", file=sys.stderr)
        return 2
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
    except (EvalError, DatasetError, OSError, ValueError) as exc:
        if args.debug:
            raise
        print(f"error: {error_line(exc, _OS_HINTS)}", file=sys.stderr)
        return 1
    for line in summary_lines(metrics):
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
