"""Figures of ``benchmarks.bench_real`` (offscreen matplotlib, via slam/evaluation/plots.py):
trajectories against the reference, a mesh close-up, and the mesh coloured by its distance to
the scan points it was built from."""

from __future__ import annotations

from pathlib import Path

import numpy as np

CLOSE_UP_RADIUS_M = 60.0
"""Half the side of the square of the MulRan map shown close up (the whole 2.6 km map is a
thin line at any picture size)."""
CLOSE_UP_FRAME = 60
"""Keyframe at the centre of the close-up: the riverside road beside an embankment wall."""
DISTANCE_MAX_M = 0.5
HEIGHT_RANGE_M = (-2.5, 3.0)
"""Heights above the sensor mapped onto the colour scale of ``mesh.png``."""


def _crop(mesh, centre: np.ndarray, radius_m: float):
    """The faces of ``mesh`` whose three vertices lie in the square of half side ``radius_m``
    around ``centre`` (x, y)."""
    vertices = np.asarray(mesh.vertices)
    inside = np.all(np.abs(vertices[:, :2] - centre[:2]) <= radius_m, axis=1)
    faces = np.asarray(mesh.faces)
    keep = inside[faces].all(axis=1)
    return mesh.submesh([np.flatnonzero(keep)], append=True), keep


def _height_colours(mesh, poses: np.ndarray) -> np.ndarray:
    """Faces coloured by height above the nearest sensor position (viridis, ``HEIGHT_RANGE_M``):
    ground dark, walls and trees bright, whatever the slope of the road."""
    from matplotlib import colormaps
    from scipy.spatial import cKDTree

    centres = np.asarray(mesh.triangles_center)
    _, nearest = cKDTree(poses[:, :2, 3]).query(centres[:, :2])
    height = centres[:, 2] - poses[nearest, 2, 3]
    low, high = HEIGHT_RANGE_M
    values = np.clip((height - low) / (high - low), 0.0, 1.0)
    return (colormaps["viridis"](values)[:, :3] * 255).astype(np.uint8)


def _mesh_figures(
    out: Path,
    mesh_path: Path,
    distances: np.ndarray,
    poses: np.ndarray,
    centre: np.ndarray | None,
    name: str,
) -> list[Path]:
    import trimesh

    from slam.evaluation import plots

    mesh = trimesh.load(mesh_path, process=False)
    vertex_colours = plots.distance_colors(distances, DISTANCE_MAX_M)
    face_colours = vertex_colours[np.asarray(mesh.faces)].mean(axis=1).astype(np.uint8)
    if centre is not None:
        mesh, keep = _crop(mesh, centre, CLOSE_UP_RADIUS_M)
        face_colours = face_colours[keep]
    view = {"elevation_deg": 55.0, "azimuth_deg": -60.0, "size_in": (7.0, 5.5), "dpi": 110}
    return [
        plots.render_mesh(
            out / "mesh.png",
            mesh,
            face_colors=_height_colours(mesh, poses),
            title=f"{name}: mesh of the neural map (colour: height above the sensor)",
            **view,
        ),
        plots.render_mesh(
            out / "mesh_distance.png",
            mesh,
            face_colors=face_colours,
            title=f"{name}: mesh vertex to nearest scan point",
            colorbar=("m", DISTANCE_MAX_M),
            **view,
        ),
    ]


def write_real_figures(out: Path, *, mulran: dict, kitti_raw: dict) -> list[Path]:
    """``real-mulran/{trajectory,mesh,mesh_distance}.png`` and
    ``real-kitti-raw/{trajectory,mesh,mesh_distance}.png`` under ``out``. Every trajectory is
    drawn in the reference's world frame, starting where the reference starts."""
    from slam.evaluation import plots

    mulran_dir, raw_dir = out / "real-mulran", out / "real-kitti-raw"
    mulran_dir.mkdir(parents=True, exist_ok=True)
    raw_dir.mkdir(parents=True, exist_ok=True)
    # a run's poses start at the identity; the reference's world frame is level (its first pose
    # is tilted by about 1 degree: 35 m of height over 2 km)
    reference = mulran["reference"]
    trajectories = {
        "reference (FAST-LIO2 + Scan Context loops)": reference,
        "FAST-LIO2 odometry": mulran["fastlio"],
        "ours: KISS-ICP odometry": reference[0] @ mulran["kiss"],
    }
    if not np.allclose(mulran["kiss_slam"], mulran["kiss"], atol=1e-3):
        trajectories["ours: SLAM (KISS-ICP + loops)"] = reference[0] @ mulran["kiss_slam"]
    diagnosis = f"KISS-ICP predicted with the reference motion (first {len(mulran['diagnosis'])})"
    trajectories[diagnosis] = reference[0] @ mulran["diagnosis"]
    poses = mulran["mesh_poses"]
    centre = poses[min(CLOSE_UP_FRAME, len(poses) - 1), :3, 3]
    title = "MulRan Riverside02 keyframes: KISS-ICP (ours) vs reference"
    figure = plots.trajectories_figure(trajectories, title=title, size_in=(7.0, 5.0), dpi=110)
    title = "KITTI raw, 22 scans: KISS-ICP (no ground truth)"
    raw = {"ours: KISS-ICP odometry": kitti_raw["poses"]}
    raw_figure = plots.trajectories_figure(raw, title=title, size_in=(6.0, 4.0), dpi=110)
    return [
        plots.save_png(figure, mulran_dir / "trajectory.png"),
        *_mesh_figures(
            mulran_dir,
            mulran["mesh"],
            mulran["distances"],
            poses,
            centre,
            "MulRan, reference poses",
        ),
        plots.save_png(raw_figure, raw_dir / "trajectory.png"),
        *_mesh_figures(
            raw_dir,
            kitti_raw["mesh"],
            kitti_raw["distances"],
            kitti_raw["poses"],
            None,
            "KITTI raw, KISS-ICP poses",
        ),
    ]
