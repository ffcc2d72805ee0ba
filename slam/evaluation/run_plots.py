"""The plots and documentation figures of an evaluated run (:mod:`slam.evaluation.cli`)."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np
import trimesh

from slam.run_folder.reader import EvalError, GroundTruth, RunTrajectories, load_map_voxels

logger = logging.getLogger("slam.eval")

PLOTS_DIR = "plots"
MESH_ERROR_MAX_M = 0.1
PLOT_SAMPLES = 50_000


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
    from slam.evaluation.metrics.trajectory import align_se3

    out = Path(run_dir) / PLOTS_DIR
    written: list[Path] = []
    try:
        _, _, anchors = load_map_voxels(run_dir)
    except (EvalError, ValueError, OSError) as exc:
        logger.warning("loop edges not drawn: %s", exc)
        anchors = {}
    edges_W = loop_edges(run_dir, anchors)
    scored = None if gt.poses is None else np.isfinite(gt.poses).all(axis=(1, 2))
    odometry = trajectories.odometry
    if gt.poses is not None:
        named = {"gt": gt.poses[scored], "slam": T_gt_W @ trajectories.slam[scored]}
        if odometry is not None:
            odometry = odometry[scored]
            named["odometry"] = align_se3(odometry, gt.poses[scored]) @ odometry
        edges = edges_W @ T_gt_W[:3, :3].T + T_gt_W[:3, 3] if len(edges_W) else edges_W
    else:
        named = {"slam": trajectories.slam}
        if odometry is not None:
            named["odometry"] = odometry
        edges = edges_W
    title = f"{Path(run_dir).name}: trajectories (top-down)"
    figure = plots.trajectories_figure(named, loop_edges=edges, title=title)
    written.append(plots.save_png(figure, out / "trajectories.png"))
    if gt.poses is not None:
        times = (trajectories.timestamps - trajectories.timestamps[0])[scored]
        errors = {
            name: np.linalg.norm(named[name][:, :3, 3] - named["gt"][:, :3, 3], axis=1)
            for name in ("odometry", "slam")
            if name in named
        }
        figure = plots.translation_error_figure(times, errors)
        written.append(plots.save_png(figure, out / "translation_error.png"))
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
        figure = plots.error_histogram_figure(distances, threshold_m=threshold_m)
        written.append(plots.save_png(figure, out / "mesh_error_histogram.png"))
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

    title = f"{name}: trajectories and loop closures"
    figure = plots.trajectories_figure(
        trajectories, loop_edges=loop_edges_gt, title=title, size_in=(5.0, 4.2), dpi=100
    )
    written = [plots.save_png(figure, out / "trajectory.png")]
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
