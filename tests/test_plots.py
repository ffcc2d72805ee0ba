"""Plots are valid PNGs of plausible size; the error-coloured mesh keeps geometry and colours."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from slam.evaluation import plots

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def assert_png(path: Path, min_width: int = 300, min_height: int = 200) -> np.ndarray:
    """The file is a PNG (signature) that decodes to an image of at least the given size and is
    not a single flat colour."""
    from matplotlib import image

    assert path.read_bytes()[:8] == PNG_SIGNATURE
    pixels = image.imread(path)
    assert pixels.ndim == 3 and pixels.shape[0] >= min_height and pixels.shape[1] >= min_width
    assert pixels[..., :3].std() > 0.01
    return pixels


def _circle(n: int, radius: float, z: float = 0.0) -> np.ndarray:
    angle = np.linspace(0, 2 * np.pi, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = radius * np.cos(angle)
    poses[:, 1, 3] = radius * np.sin(angle)
    poses[:, 2, 3] = z
    return poses


def test_top_down_axes_pick_the_ground_plane() -> None:
    positions = np.stack([np.zeros(50), np.linspace(0, 10, 50), np.linspace(0, 4, 50)], axis=1)
    assert plots.top_down_axes(positions) == (1, 2)
    assert plots.top_down_axes(_circle(40, 5.0)[:, :3, 3]) == (0, 1)


def test_trajectory_and_error_plots_are_pngs(tmp_path: Path) -> None:
    gt = _circle(100, 10.0)
    odometry = _circle(100, 10.5)
    slam = _circle(100, 10.1)
    edges = np.stack([slam[[0, 10], :3, 3], slam[[99, 60], :3, 3]], axis=1)
    path = plots.plot_trajectories_top_down(
        tmp_path / "traj.png", {"gt": gt, "odometry": odometry, "slam": slam}, loop_edges=edges
    )
    assert_png(path)
    errors = {"odometry": np.linspace(0, 0.5, 100), "slam": np.full(100, 0.1)}
    assert_png(plots.plot_translation_error(tmp_path / "err.png", np.arange(100) * 0.1, errors))
    distances = {"accuracy": np.abs(np.random.default_rng(0).normal(0, 0.02, 1000))}
    assert_png(plots.plot_error_histogram(tmp_path / "hist.png", distances, threshold_m=0.05))
    groups = {"accuracy": {"transform": [0.01, 0.02], "re-encode": [0.005, 0.01]}}
    assert_png(plots.plot_distributions(tmp_path / "box.png", groups))
    assert not list(tmp_path.glob(".*.tmp"))


def test_error_colored_mesh_round_trips(tmp_path: Path) -> None:
    mesh = trimesh.creation.icosphere(subdivisions=2)
    distances = np.linspace(0.0, 0.2, len(mesh.vertices))
    path = plots.write_error_colored_mesh(tmp_path / "err.ply", mesh, distances, max_m=0.1)
    loaded = trimesh.load(path, process=False)
    assert len(loaded.vertices) == len(mesh.vertices) and len(loaded.faces) == len(mesh.faces)
    colors = np.asarray(loaded.visual.vertex_colors)[:, :3].astype(int)
    # Blue at zero error, red beyond max_m.
    assert colors[0, 2] > colors[0, 0] and colors[-1, 0] > colors[-1, 2]
