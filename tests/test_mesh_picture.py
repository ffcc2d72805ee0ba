"""Top-down mesh pictures: the corner is the often-passed sharp turn, and a generated box on a
ground plate shows in the PNG in the colours of its heights where its faces are, the trajectory
over it, and background where no face lies."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from matplotlib import colormaps
from matplotlib.colors import Normalize

from benchmarks.harness import mesh_picture
from benchmarks.harness.mesh_picture import Panel
from tests.helpers import colour_mask, png_pixels, positions_along

SENSOR_HEIGHT_M = 1.7


def _path(*points: tuple[float, float]) -> np.ndarray:
    return positions_along(points, 0.5, SENSOR_HEIGHT_M)


def test_corner_is_the_sharp_turn_the_trajectory_passes_most_often() -> None:
    # an L driven once (turn at 200, 0), then a square whose corner (0, 0) is passed twice
    once = _path((100, 0), (200, 0), (200, 100))
    loop = _path((-50, 0), (0, 0), (0, -60), (-60, -60), (-60, 0), (0, 0), (0, 60))
    corner = mesh_picture.street_corner(np.concatenate([once, loop]))
    np.testing.assert_allclose(corner.centre_W[:2], [0, 0], atol=0.6)
    assert corner.passes == 2 and 80 < corner.turn_deg < 100
    alone = mesh_picture.street_corner(once)
    np.testing.assert_allclose(alone.centre_W[:2], [200, 0], atol=0.6)
    assert alone.passes == 1


def _colour(height_m: float) -> tuple[float, float, float]:
    norm = Normalize(*mesh_picture.HEIGHT_RANGE_M)
    return colormaps[mesh_picture.HEIGHT_COLOURS](norm(height_m))[:3]


def test_box_on_a_plate_shows_its_heights_where_its_faces_are(tmp_path: Path) -> None:
    plate = trimesh.creation.box(extents=(30, 20, 0.01))  # ground 1.7 m below the sensor
    plate.apply_translation((-10, 0, 0))
    box = trimesh.creation.box(extents=(8, 8, 3.0))  # top 1.5 m above the sensor
    box.apply_translation((16, 10, 1.5))
    mesh = trimesh.util.concatenate([plate, box])
    positions = _path((-40, -15), (40, -15))
    corner = mesh_picture.Corner(scan=0, centre_W=np.zeros(3), turn_deg=0.0, passes=1)
    heights = mesh_picture.height_map(mesh.vertices, mesh.faces, positions, corner.centre_W)
    figure = mesh_picture.corner_figure([[Panel("box", heights, positions)]], corner)
    path = mesh_picture.write_png(tmp_path / "corner.png", figure)
    assert path.stat().st_size < 400_000 and not list(tmp_path.glob(".*.tmp"))
    pixels = png_pixels(path)
    axes = figure.axes[0]

    def at(x_m: float, y_m: float, radius_px: int = 3) -> np.ndarray:
        x, y = axes.transData.transform([x_m, y_m])
        row, col = round(pixels.shape[0] - y), round(x)
        return pixels[row - radius_px : row + radius_px + 1, col - radius_px : col + radius_px + 1]

    ground, top = _colour(-SENSOR_HEIGHT_M), _colour(3.0 - SENSOR_HEIGHT_M)
    for x, y in [(-20, 5), (-5, -5), (0, 8)]:  # on the plate
        assert colour_mask(at(x, y), ground).all(), (x, y)
        assert not colour_mask(at(x, y), top).any(), (x, y)
    for x, y in [(14, 8), (18, 12), (16, 10)]:  # on the box
        assert colour_mask(at(x, y), top).all(), (x, y)
    for x, y in [(-30, 30), (30, -5), (10, 30)]:  # nothing there
        assert colour_mask(at(x, y), mesh_picture.BACKGROUND).all(), (x, y)
    trajectory = colour_mask(at(0, -15, 1), mesh_picture.TRAJECTORY_COLOUR)
    assert trajectory.any() and not colour_mask(at(0, 5), mesh_picture.TRAJECTORY_COLOUR).any()


def test_height_map_is_empty_without_faces_in_the_window() -> None:
    far = trimesh.creation.box(extents=(2, 2, 2))
    far.apply_translation((500, 0, 0))
    positions = _path((-40, 0), (40, 0))
    heights = mesh_picture.height_map(far.vertices, far.faces, positions, np.zeros(3))
    assert heights.shape == (mesh_picture.PANEL_PIXELS,) * 2 and np.isnan(heights).all()
