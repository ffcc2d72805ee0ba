"""The picture of ``benchmarks.bench_lidar_map``: one street corner of its meshes, top down.

Rows: the maps built from ground-truth poses and from SLAM poses (aligned onto the ground truth
as their scores are); columns: the neural map before (``--before-set``) and as configured, with
the ground-truth mesh of the same window beside them (``benchmarks.harness.mesh_picture``).
"""

from __future__ import annotations

from pathlib import Path

from benchmarks.lidar_map_report import BEFORE_ROWS

PICTURED = {BEFORE_ROWS: "before", "neural map": "as configured"}
"""The neural-map rows pictured (columns), as the caption names them."""
POSE_ROWS = {"gt": "ground-truth poses", "kiss-icp": "SLAM poses"}
"""The kinds of run pictured (rows)."""


def corner_panels(runs: dict, scorer, max_ranges_m: dict[str, float]):
    """The corner (``mesh_picture.Corner``) and the rows of panels of the maps
    ``runs[kind][name]`` (kinds of :data:`POSE_ROWS`, names of ``max_ranges_m``, each with the
    range its map holds), each mesh and trajectory aligned onto the ground truth by its poses,
    and of the ground-truth mesh (``scorer``: a ``StreetScorer``)."""
    from benchmarks.harness import mesh_picture
    from slam.evaluation.metrics.trajectory import align_se3

    positions = scorer.gt_poses[:, :3, 3]
    corner = mesh_picture.street_corner(positions)
    rows = []
    for kind, poses_name in POSE_ROWS.items():
        row = []
        for name, max_range_m in max_ranges_m.items():
            result = runs[kind][name]
            T = align_se3(result["poses"], scorer.gt_poses)
            vertices = result["vertices"] @ T[:3, :3].T + T[:3, 3]
            heights = mesh_picture.height_map(vertices, result["faces"], positions, corner.centre_W)
            trajectory = (T @ result["poses"])[:, :3, 3]
            title = f"{poses_name}, {_column(name, max_range_m)}"
            row.append(mesh_picture.Panel(title, heights, trajectory))
        rows.append(row)
    gt = scorer.gt_region
    truth = mesh_picture.height_map(gt.vertices, gt.faces, positions, corner.centre_W)
    rows[0].append(mesh_picture.Panel("ground-truth mesh", truth, positions))
    return corner, rows


def _column(name: str, max_range_m: float) -> str:
    return f"map to {max_range_m:g} m ({PICTURED[name]})"


def corner_picture(path: Path, runs: dict, scorer, max_ranges_m: dict[str, float]) -> str:
    """The picture of :func:`corner_panels`, with an overview of the trajectory, written to
    ``path``. Returns its one-line caption."""
    from benchmarks.harness import mesh_picture

    corner, rows = corner_panels(runs, scorer, max_ranges_m)
    figure = mesh_picture.corner_figure(
        rows,
        corner,
        overview_W=scorer.gt_poses[:, :3, 3],
        title=f"Street corner: {corner.describe()}",
    )
    mesh_picture.write_png(path, figure)
    columns = ", ".join(_column(name, r) for name, r in max_ranges_m.items())
    return (
        f"Street corner, {corner.describe()}, top down. Rows: {', '.join(POSE_ROWS.values())} "
        f"(aligned onto the ground truth); columns: {columns}, the ground-truth mesh. Colour: "
        "height above the nearest sensor position (white: no surface); red: the trajectory."
    )
