"""Top-down pictures of LiDAR meshes over one street corner, coloured by height.

A mesh is drawn as a height map: points sampled uniformly over its faces in the window, each
pixel holding the highest sample's height above the nearest sensor position (the road dark,
kerbs and walls bright whatever the slope; a pixel no face covers stays background). The corner
is chosen from the ground-truth positions alone (:func:`street_corner`), so that every picture
of one run shows the same square.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

WINDOW_SIDE_M = 80.0
"""Side of the square window around the corner."""
PANEL_PIXELS = 480
"""Height-map pixels along a side of the window."""
SAMPLES_PER_PIXEL = 8.0
"""Mesh samples per pixel area of surface (a pixel of flat ground stays empty with odds
e^-8)."""
MAX_SAMPLES = 40_000_000
"""Samples of one height map at most: bounds the time a mesh of huge faces takes."""
CHUNK_SAMPLES = 2_000_000
"""Samples, or faces, held at once."""
HEIGHT_RANGE_M = (-2.5, 3.5)
"""Heights above the nearest sensor position spread over the colour scale (the road lies about
1.7 m below a car's LiDAR)."""
HEIGHT_COLOURS = "viridis"
TRAJECTORY_COLOUR = "tab:red"
BACKGROUND = "white"
TURN_ARM_M = 15.0
"""A turn is the heading change between the trajectory this far before and after a scan."""
MIN_TURN_DEG = 45.0
"""Turns at least this sharp are corners; among them the most often passed one is chosen."""
PALETTE_COLOURS = 256
"""The PNG holds an adaptive palette of this many colours (the street corner: 196 kB, against
365 kB in RGB)."""


@dataclass(frozen=True)
class Corner:
    """The window's centre: a scan of the run, its turn and how often the run passes there."""

    scan: int
    centre_W: np.ndarray
    turn_deg: float
    passes: int

    def describe(self, side_m: float = WINDOW_SIDE_M) -> str:
        times = "once" if self.passes == 1 else f"{self.passes} times"
        return (
            f"{side_m:g} m square centred on scan {self.scan}, a {self.turn_deg:.0f} deg turn "
            f"the run passes {times} (of its sharp turns, the most often passed)"
        )


def turn_angles_deg(positions_W: np.ndarray, arm_m: float = TURN_ARM_M) -> np.ndarray:
    """Heading change (degrees, in the x-y plane) at each position, between the travel
    ``arm_m`` before it and the travel ``arm_m`` after it (0 where either is shorter than 1 m)."""
    xy = positions_W[:, :2]
    travelled = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
    before = np.searchsorted(travelled, travelled - arm_m)
    after = np.minimum(np.searchsorted(travelled, travelled + arm_m), len(xy) - 1)
    incoming, outgoing = xy - xy[before], xy[after] - xy
    cross = incoming[:, 0] * outgoing[:, 1] - incoming[:, 1] * outgoing[:, 0]
    angles = np.abs(np.degrees(np.arctan2(cross, np.sum(incoming * outgoing, axis=1))))
    short = (np.linalg.norm(incoming, axis=1) < 1.0) | (np.linalg.norm(outgoing, axis=1) < 1.0)
    return np.where(short, 0.0, angles)


def passes_near(positions_W: np.ndarray, centre_W: np.ndarray, radius_m: float) -> int:
    """How many separate times the trajectory enters the disc of ``radius_m`` around
    ``centre_W`` (x-y)."""
    inside = np.linalg.norm(positions_W[:, :2] - centre_W[:2], axis=1) <= radius_m
    return int(inside[0]) + int(np.sum(np.diff(inside.astype(int)) == 1))


def street_corner(positions_W: np.ndarray, side_m: float = WINDOW_SIDE_M) -> Corner:
    """The corner the window is centred on: among the scans turning by at least
    :data:`MIN_TURN_DEG`, the one whose window the trajectory passes most often, the sharpest
    turn among those; the sharpest turn of all when none is that sharp."""
    turns = turn_angles_deg(positions_W)
    candidates = np.flatnonzero(turns >= MIN_TURN_DEG)
    if len(candidates) == 0:
        candidates = np.array([int(np.argmax(turns))])
    passes = np.array([passes_near(positions_W, positions_W[i], side_m / 2) for i in candidates])
    chosen = np.lexsort((-turns[candidates], -passes))[0]
    best = candidates[chosen]
    return Corner(int(best), positions_W[best].copy(), float(turns[best]), int(passes[chosen]))


def _window_triangles(vertices_W, faces, window_low: np.ndarray, side_m: float) -> np.ndarray:
    """The triangles (F, 3, 3) of the faces whose x-y bounds meet the window, gathered
    :data:`CHUNK_SAMPLES` faces at a time (a whole run's mesh is millions of faces)."""
    vertices_W = np.asarray(vertices_W)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    kept = []
    for start in range(0, len(faces), CHUNK_SAMPLES):
        triangles = vertices_W[faces[start : start + CHUNK_SAMPLES]]
        low, high = triangles[..., :2].min(axis=1), triangles[..., :2].max(axis=1)
        kept.append(triangles[np.all((high >= window_low) & (low <= window_low + side_m), axis=1)])
    return np.concatenate(kept) if kept else np.zeros((0, 3, 3))


def _window_samples(triangles_W, side_m: float, pixels: int, seed: int) -> Iterator[np.ndarray]:
    """Points drawn uniformly over the triangles (F, 3, 3) of :func:`_window_triangles`,
    :data:`SAMPLES_PER_PIXEL` per pixel area of their surface, :data:`CHUNK_SAMPLES` at a
    time (a large triangle reaching past the window spends samples outside it, but leaves no
    pixel inside it short)."""
    edges = triangles_W[:, 1:] - triangles_W[:, :1]
    areas = 0.5 * np.linalg.norm(np.cross(edges[:, 0], edges[:, 1]), axis=1)
    if areas.sum() <= 0:
        return
    wanted = SAMPLES_PER_PIXEL * areas.sum() * (pixels / side_m) ** 2
    count = int(min(MAX_SAMPLES, max(1.0, wanted)))
    rng = np.random.default_rng(seed)
    for start in range(0, count, CHUNK_SAMPLES):
        size = min(CHUNK_SAMPLES, count - start)
        chosen = rng.choice(len(triangles_W), size=size, p=areas / areas.sum())
        u, v = rng.random((2, size))
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        yield triangles_W[chosen, 0] + u[:, None] * edges[chosen, 0] + v[:, None] * edges[chosen, 1]


def height_map(
    vertices_W: np.ndarray,
    faces: np.ndarray,
    positions_W: np.ndarray,
    centre_W: np.ndarray,
    side_m: float = WINDOW_SIDE_M,
    pixels: int = PANEL_PIXELS,
    seed: int = 0,
) -> np.ndarray:
    """The top-down height map (``pixels`` x ``pixels``, row 0 at the window's lowest y; NaN
    where no face lies) of a mesh over the square of side ``side_m`` around ``centre_W``: the
    highest sample of each pixel, above the sensor position of ``positions_W`` nearest to the
    pixel."""
    from scipy.spatial import cKDTree

    window_low = np.asarray(centre_W[:2]) - side_m / 2
    pixel_m = side_m / pixels
    top = np.full(pixels * pixels, -np.inf)
    triangles = _window_triangles(vertices_W, faces, window_low, side_m)
    for samples in _window_samples(triangles, side_m, pixels, seed):
        cells = np.floor((samples[:, :2] - window_low) / pixel_m).astype(np.int64)
        inside = np.all((cells >= 0) & (cells < pixels), axis=1)
        cells = cells[inside]
        np.maximum.at(top, cells[:, 1] * pixels + cells[:, 0], samples[inside, 2])
    offsets = (np.arange(pixels) + 0.5) * pixel_m
    x, y = np.meshgrid(window_low[0] + offsets, window_low[1] + offsets, indexing="xy")
    grid = np.column_stack([x.ravel(), y.ravel()])
    _, nearest = cKDTree(positions_W[:, :2]).query(grid, workers=-1)
    heights = np.where(np.isneginf(top), np.nan, top - positions_W[nearest, 2])
    return heights.reshape(pixels, pixels)


@dataclass
class Panel:
    """One picture of the grid: its title, height map and the trajectory drawn over it."""

    title: str
    heights: np.ndarray
    trajectory_W: np.ndarray


def corner_figure(
    rows: list[list[Panel]],
    corner: Corner,
    overview_W: np.ndarray | None = None,
    side_m: float = WINDOW_SIDE_M,
    title: str = "",
):
    """A grid of height maps (``rows`` of panels, a blank cell where a row is shorter), axes in
    metres from the corner; with ``overview_W``, the whole trajectory and the window's square in
    the last cell of the last row, which must be blank."""
    from matplotlib import colormaps
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    columns = max(len(row) for row in rows)
    if overview_W is not None and len(rows[-1]) == columns:
        raise ValueError("the overview needs a blank last cell: the last row is full")
    figure = Figure(figsize=(5.4 * columns, 5.4 * len(rows) + 0.7), dpi=100)
    grid = figure.subplots(len(rows), columns, squeeze=False)
    colours = colormaps[HEIGHT_COLOURS].with_extremes(bad=BACKGROUND)
    norm = Normalize(*HEIGHT_RANGE_M)
    half = side_m / 2
    centre = np.asarray(corner.centre_W[:2])
    image = None
    for row, cells in zip(grid, rows, strict=True):
        for axes, panel in zip(row, cells, strict=False):
            image = axes.imshow(
                panel.heights,
                origin="lower",
                extent=(-half, half, -half, half),
                cmap=colours,
                norm=norm,
                interpolation="nearest",
            )
            path = panel.trajectory_W[:, :2] - centre
            axes.plot(path[:, 0], path[:, 1], color=TRAJECTORY_COLOUR, linewidth=1.6)
            axes.set_xlim(-half, half)
            axes.set_ylim(-half, half)
            axes.set_title(panel.title, fontsize=11)
            axes.tick_params(labelsize=8)
        for axes in row[len(cells) :]:
            axes.set_axis_off()
    if overview_W is not None:
        axes = grid[-1, -1]
        axes.set_axis_on()
        axes.plot(overview_W[:, 0], overview_W[:, 1], color=TRAJECTORY_COLOUR, linewidth=1.0)
        axes.add_patch(
            Rectangle(tuple(centre - half), side_m, side_m, fill=False, edgecolor="black")
        )
        axes.set_aspect("equal", adjustable="datalim")
        axes.set_title("trajectory and the window [m]", fontsize=11)
        axes.tick_params(labelsize=8)
    figure.suptitle(title, fontsize=12, wrap=True)
    figure.subplots_adjust(left=0.04, right=0.98, top=0.93, bottom=0.08, wspace=0.18, hspace=0.2)
    if image is not None:
        bar = figure.colorbar(
            image,
            ax=grid.ravel().tolist(),
            orientation="horizontal",
            fraction=0.03,
            pad=0.06,
            aspect=60,
        )
        bar.set_label("height above the nearest sensor position [m] (white: no surface)")
    return figure


def write_png(path: str | Path, figure) -> Path:
    """``figure`` written atomically as a palette PNG."""
    from slam.evaluation.plots import palette_png, save_png

    return palette_png(save_png(figure, path), PALETTE_COLOURS)
