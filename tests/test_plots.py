"""Plots show their data: the figures' lines, bars and boxes hold the given values in the
given styles, the trajectories land at their places on the canvas, and every PNG written is the
figure drawn from that data, pixel for pixel. The error-coloured mesh keeps geometry and colours."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from matplotlib.colors import to_rgb

from slam.evaluation import plots
from tests.helpers import assert_png_shows, colour_mask, figure_pixels


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


def _lines_by_label(axes) -> dict[str, object]:
    return {line.get_label(): line for line in axes.lines}


def test_trajectory_plot_draws_each_trajectory_and_loop_edge_in_its_style(tmp_path: Path) -> None:
    gt, odometry, slam = _circle(100, 10.0), _circle(100, 10.5), _circle(100, 10.1)
    trajectories = {"gt": gt, "odometry": odometry, "slam": slam}
    edges = np.stack([slam[[0, 10], :3, 3], slam[[99, 60], :3, 3]], axis=1)
    figure = plots.trajectories_figure(trajectories, loop_edges=edges)
    (axes,) = figure.axes
    lines = _lines_by_label(axes)
    for name, poses in trajectories.items():
        style = plots.TRAJECTORY_STYLES[name]
        line = lines[style["label"]]
        np.testing.assert_allclose(line.get_xdata(), poses[:, 0, 3])  # top-down: x and y
        np.testing.assert_allclose(line.get_ydata(), poses[:, 1, 3])
        assert to_rgb(line.get_color()) == to_rgb(style["color"])
    loops = [line for line in axes.lines if to_rgb(line.get_color()) == to_rgb("tab:green")]
    assert len(loops) == 2 and loops[0].get_label() == "loop closures (2)"
    for line, (p, q) in zip(loops, edges, strict=True):
        np.testing.assert_allclose(line.get_xydata(), [p[:2], q[:2]])
    np.testing.assert_allclose(lines["start"].get_xydata(), [gt[0, :2, 3]])

    # On the canvas: SLAM blue where the SLAM circle is, none around the circle's centre.
    pixels = figure_pixels(figure)
    blue = colour_mask(pixels, "tab:blue")

    def near(x_m: float, y_m: float, radius_px: int) -> np.ndarray:
        x, y = axes.transData.transform([x_m, y_m])
        row, col = round(pixels.shape[0] - y), round(x)
        return blue[row - radius_px : row + radius_px + 1, col - radius_px : col + radius_px + 1]

    for angle in np.radians([30.0, 120.0, 250.0]):
        assert near(10.1 * np.cos(angle), 10.1 * np.sin(angle), 2).any(), angle
    assert not near(0.0, 0.0, 20).any()
    path = plots.save_png(figure, tmp_path / "traj.png")
    assert_png_shows(path, plots.trajectories_figure(trajectories, loop_edges=edges))
    assert not list(tmp_path.glob(".*.tmp"))


def test_translation_error_plot_draws_each_error_over_time(tmp_path: Path) -> None:
    times = np.arange(100) * 0.1
    errors = {"odometry": np.linspace(0, 0.5, 100), "slam": np.full(100, 0.1)}
    figure = plots.translation_error_figure(times, errors)
    lines = figure.axes[0].lines
    assert [line.get_label() for line in lines] == [
        f"odometry (RMSE {np.sqrt(np.mean(errors['odometry'] ** 2)):.3f} m)",
        "SLAM (loop-closed) (RMSE 0.100 m)",
    ]
    for line, (name, error) in zip(lines, errors.items(), strict=True):
        np.testing.assert_allclose(line.get_xdata(), times)
        np.testing.assert_allclose(line.get_ydata(), error)
        assert to_rgb(line.get_color()) == to_rgb(plots.TRAJECTORY_STYLES[name]["color"])
    path = plots.save_png(figure, tmp_path / "err.png")
    assert_png_shows(path, plots.translation_error_figure(times, errors))


def test_error_histogram_counts_every_sample_and_marks_the_threshold(tmp_path: Path) -> None:
    # 1 cm x 150, 3 cm x 50, one 1 m outlier: the 99th percentile is 3 cm, so the range is
    # 1.5 x the 5 cm threshold and the outlier lands in the last bin
    distances = {"accuracy": np.r_[np.full(150, 0.01), np.full(50, 0.03), 1.0]}
    figure = plots.error_histogram_figure(distances, threshold_m=0.05)
    (axes,) = figure.axes
    (bars,) = axes.containers
    heights = np.array([bar.get_height() for bar in bars])
    left = np.array([bar.get_x() for bar in bars])
    width = bars[0].get_width()
    assert len(bars) == 59 and np.isclose(left[-1] + width, 0.075)
    assert heights.sum() == 201 and heights[-1] == 1
    assert heights[int(0.01 // width)] == 150 and heights[int(0.03 // width)] == 50
    (threshold,) = [line for line in axes.lines if line.get_linestyle() == ":"]
    np.testing.assert_allclose(threshold.get_xdata(), [0.05, 0.05])
    path = plots.save_png(figure, tmp_path / "hist.png")
    assert_png_shows(path, plots.error_histogram_figure(distances, threshold_m=0.05))


def test_distribution_plot_has_one_panel_per_group_and_one_box_per_series(tmp_path: Path) -> None:
    groups = {
        "accuracy": {"transform": [0.01, 0.02, 0.03], "re-encode": [0.005, 0.01, 0.015]},
        "completion": {"transform": [0.02, 0.04, 0.06], "re-encode": [0.01, 0.01, 0.04]},
    }
    figure = plots.distributions_figure(groups)
    assert [axes.get_title() for axes in figure.axes] == list(groups)
    for axes, series in zip(figure.axes, groups.values(), strict=True):
        assert [label.get_text() for label in axes.get_xticklabels()] == list(series)
        for position, values in enumerate(series.values(), start=1):
            cm = 100.0 * np.asarray(values)
            # the horizontal strokes of a box: the whisker caps, the quartiles and the median
            strokes = {
                round(float(line.get_ydata()[0]), 6)
                for line in axes.lines
                if len(line.get_xdata()) >= 2
                and abs(np.mean(line.get_xdata()) - position) < 0.3
                and np.ptp(line.get_ydata()) == 0
            }
            assert {round(float(v), 6) for v in (cm.min(), np.median(cm), cm.max())} <= strokes
            means = [line for line in axes.lines if list(line.get_xdata()) == [position]]
            assert means and np.isclose(means[0].get_ydata()[0], cm.mean())
    path = plots.save_png(figure, tmp_path / "box.png")
    assert_png_shows(path, plots.distributions_figure(groups))


def test_error_colored_mesh_round_trips(tmp_path: Path) -> None:
    mesh = trimesh.creation.icosphere(subdivisions=2)
    distances = np.linspace(0.0, 0.2, len(mesh.vertices))
    path = plots.write_error_colored_mesh(tmp_path / "err.ply", mesh, distances, max_m=0.1)
    loaded = trimesh.load(path, process=False)
    assert len(loaded.vertices) == len(mesh.vertices) and len(loaded.faces) == len(mesh.faces)
    colors = np.asarray(loaded.visual.vertex_colors)[:, :3].astype(int)
    # Blue at zero error, red beyond max_m.
    assert colors[0, 2] > colors[0, 0] and colors[-1, 0] > colors[-1, 2]
