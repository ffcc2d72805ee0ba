"""PNG plots and an error-coloured mesh for evaluating a run.

Figures are drawn with matplotlib's object API on an Agg canvas (no pyplot, no global backend
switch), so they can be produced from any thread or a headless machine. Every writer saves to a
temporary file first and renames it into place.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from common.atomic_io import atomic_path, write_bytes_atomic

if TYPE_CHECKING:
    from matplotlib.figure import Figure

TRAJECTORY_STYLES: dict[str, dict[str, object]] = {
    "gt": {"color": "0.2", "linestyle": "--", "linewidth": 1.2, "label": "GT", "zorder": 4},
    "odometry": {"color": "tab:orange", "linewidth": 1.2, "label": "odometry", "zorder": 2},
    "slam": {"color": "tab:blue", "linewidth": 1.4, "label": "SLAM (loop-closed)", "zorder": 3},
}


def _new_figure(width_in: float = 7.0, height_in: float = 5.0) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width_in, height_in), dpi=120, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def save_png(figure: Figure, path: Path) -> Path:
    """Write ``figure`` as a PNG at ``path`` (atomically); returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        figure.savefig(tmp, format="png")
    return path


def _positions(poses_or_positions: np.ndarray) -> np.ndarray:
    array = np.asarray(poses_or_positions, dtype=np.float64)
    return array[:, :3, 3] if array.ndim == 3 else array.reshape(-1, 3)


def top_down_axes(positions: np.ndarray) -> tuple[int, int]:
    """The two world axes with the largest spread of ``positions`` (the ground plane of a
    ground vehicle or hand-held camera), in increasing index order."""
    spread = np.ptp(np.asarray(positions, dtype=np.float64).reshape(-1, 3), axis=0)
    first, second = sorted(np.argsort(spread)[-2:])
    return int(first), int(second)


def trajectories_figure(
    trajectories: Mapping[str, np.ndarray],
    *,
    loop_edges: np.ndarray | None = None,
    title: str = "",
    size_in: tuple[float, float] = (7.0, 6.0),
    dpi: int = 120,
) -> Figure:
    """Top-down view of trajectories (``gt``, ``odometry``, ``slam`` or any name) and accepted
    loop edges, given as (M, 2, 3) world positions, drawn on the ``slam`` trajectory. Each
    trajectory is the line labelled with its style's label, each loop edge a two-point line."""
    named = {name: _positions(poses) for name, poses in trajectories.items() if len(poses)}
    reference = named.get("gt", next(iter(named.values()), np.zeros((1, 3))))
    a, b = top_down_axes(reference)
    figure = _new_figure(*size_in)
    figure.set_dpi(dpi)
    axes = figure.add_subplot()
    for name, positions in named.items():
        style = dict(TRAJECTORY_STYLES.get(name, {"label": name, "linewidth": 1.2}))
        axes.plot(positions[:, a], positions[:, b], **style)
    if loop_edges is not None and len(loop_edges):
        edges = np.asarray(loop_edges, dtype=np.float64).reshape(-1, 2, 3)
        for index, (p, q) in enumerate(edges):
            axes.plot(
                [p[a], q[a]],
                [p[b], q[b]],
                color="tab:green",
                linewidth=1.0,
                label=f"loop closures ({len(edges)})" if index == 0 else None,
            )
    start = reference[0]
    axes.plot(start[a], start[b], marker="o", color="black", linestyle="none", label="start")
    axes.set_aspect("equal", adjustable="datalim")
    axes.set_xlabel(f"{'xyz'[a]} [m]")
    axes.set_ylabel(f"{'xyz'[b]} [m]")
    axes.grid(True, alpha=0.3)
    axes.legend(loc="best", fontsize=8)
    axes.set_title(title or "Trajectories (top-down)")
    return figure


def translation_error_figure(
    times: np.ndarray,
    errors_m: Mapping[str, np.ndarray],
    *,
    time_label: str = "time [s]",
    title: str = "",
) -> Figure:
    """Per-frame position error (metres, after alignment) of each trajectory over time, one
    line per trajectory labelled with its RMSE."""
    figure = _new_figure(8.0, 4.0)
    axes = figure.add_subplot()
    for name, error in errors_m.items():
        style = dict(TRAJECTORY_STYLES.get(name, {"label": name}))
        style.pop("linestyle", None)
        rmse = float(np.sqrt(np.mean(np.square(error)))) if len(error) else float("nan")
        style["label"] = f"{style.get('label', name)} (RMSE {rmse:.3f} m)"
        axes.plot(np.asarray(times)[: len(error)], error, **style)
    axes.set_xlabel(time_label)
    axes.set_ylabel("translation error [m]")
    axes.grid(True, alpha=0.3)
    axes.legend(loc="best", fontsize=8)
    axes.set_title(title or "Absolute translation error (SE(3)-aligned)")
    return figure


def error_histogram_figure(
    distances_m: Mapping[str, np.ndarray],
    *,
    threshold_m: float | None = 0.05,
    title: str = "",
) -> Figure:
    """Histograms of surface distances, e.g. ``{"accuracy": pred->gt, "completion": gt->pred}``,
    and the threshold as a vertical line; the last bin holds the 1% tail."""
    figure = _new_figure(7.0, 4.0)
    axes = figure.add_subplot()
    finite = [np.asarray(d)[np.isfinite(d)] for d in distances_m.values()]
    upper = max((float(np.percentile(d, 99.0)) for d in finite if len(d)), default=0.1)
    if threshold_m is not None:
        upper = max(upper, 1.5 * threshold_m)
    bins = np.linspace(0.0, upper, 60)
    for (name, _), values in zip(distances_m.items(), finite, strict=True):
        mean = float(values.mean()) if len(values) else float("nan")
        axes.hist(
            np.clip(values, 0.0, upper),
            bins=bins,
            alpha=0.55,
            label=f"{name} (mean {100 * mean:.2f} cm)",
        )
    if threshold_m is not None:
        axes.axvline(threshold_m, color="black", linestyle=":", label=f"{100 * threshold_m:g} cm")
    axes.set_xlabel("distance [m] (last bin holds the 1% tail)")
    axes.set_ylabel("samples")
    axes.legend(loc="best", fontsize=8)
    axes.set_title(title or "Mesh error distribution")
    return figure


def distributions_figure(
    groups: Mapping[str, Mapping[str, Sequence[float]]],
    *,
    ylabel: str = "distance [cm]",
    scale: float = 100.0,
    title: str = "",
) -> Figure:
    """Side-by-side box plots: one panel per group (e.g. ``accuracy``), one box per series (e.g.
    ``transform`` vs ``re-encode``), values multiplied by ``scale``."""
    figure = _new_figure(4.0 * max(1, len(groups)), 4.5)
    panels = figure.subplots(1, max(1, len(groups)), squeeze=False)[0]
    for axes, (group, series) in zip(panels, groups.items(), strict=False):
        labels = list(series)
        data = [np.asarray(series[label], dtype=np.float64) * scale for label in labels]
        axes.boxplot(data, showmeans=True)
        axes.set_xticks(range(1, len(labels) + 1), labels)
        axes.set_title(group)
        axes.set_ylabel(ylabel)
        axes.grid(True, axis="y", alpha=0.3)
    if title:
        figure.suptitle(title)
    return figure


def distance_colors(distances_m: np.ndarray, max_m: float) -> np.ndarray:
    """(N,) distances -> (N, 4) uint8 RGBA on a blue (0) to red (``max_m`` and beyond) scale."""
    from matplotlib import colormaps

    scaled = np.clip(np.nan_to_num(np.asarray(distances_m, float), nan=max_m) / max_m, 0.0, 1.0)
    return np.asarray(colormaps["jet"](scaled, bytes=True))


def write_error_colored_mesh(
    path: Path, mesh: trimesh.Trimesh, vertex_distances_m: np.ndarray, *, max_m: float = 0.1
) -> Path:
    """Write ``mesh`` as PLY with vertex colours encoding the distance of each vertex to ground
    truth (blue 0 m -> red >= ``max_m``)."""
    colored = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices),
        faces=np.asarray(mesh.faces),
        vertex_colors=distance_colors(vertex_distances_m, max_m),
        process=False,
    )
    path = Path(path)
    write_bytes_atomic(path, trimesh.exchange.ply.export_ply(colored, encoding="binary"))
    return path


UP_VECTORS: dict[str, np.ndarray] = {
    "+x": np.array([1.0, 0.0, 0.0]),
    "-x": np.array([-1.0, 0.0, 0.0]),
    "+y": np.array([0.0, 1.0, 0.0]),
    "-y": np.array([0.0, -1.0, 0.0]),
    "+z": np.array([0.0, 0.0, 1.0]),
    "-z": np.array([0.0, 0.0, -1.0]),
}


def _view_basis(up: np.ndarray, elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Rows ``right, screen_up, towards_viewer`` of an orthographic camera looking down at
    ``elevation_deg`` from ``azimuth_deg`` around the world's ``up``."""
    up = up / np.linalg.norm(up)
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    east = np.cross(helper, up)
    east /= np.linalg.norm(east)
    north = np.cross(up, east)
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    horizontal = np.cos(az) * east + np.sin(az) * north
    towards_viewer = np.cos(el) * horizontal + np.sin(el) * up
    right = np.cross(up, towards_viewer)
    right /= np.linalg.norm(right)
    screen_up = np.cross(towards_viewer, right)
    return np.stack([right, screen_up, towards_viewer])


def render_mesh(
    path: Path,
    mesh: trimesh.Trimesh,
    *,
    face_colors: np.ndarray | None = None,
    up_axis: str = "+z",
    elevation_deg: float = 60.0,
    azimuth_deg: float = -60.0,
    title: str = "",
    colorbar: tuple[str, float] | None = None,
    size_in: tuple[float, float] = (5.0, 4.0),
    dpi: int = 100,
) -> Path:
    """A shaded offscreen snapshot of ``mesh`` (orthographic, painter's algorithm on an Agg
    canvas: no display, no GPU).

    Faces turned away from the viewer are culled, which opens rooms and streets from above (the
    "doll's house" view); the remaining faces are drawn far to near with Lambertian shading.
    ``face_colors`` (F, 3 or 4) uint8 colour each face (default: light grey); ``colorbar =
    (label, max)`` adds a jet colour bar from 0 to ``max``.
    """
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import Normalize

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    basis = _view_basis(UP_VECTORS[up_axis], elevation_deg, azimuth_deg)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)
    facing = normals @ basis[2]
    if np.count_nonzero(facing > 0) < 0.2 * len(faces):  # winding opposite to the convention
        facing = -facing
    keep = facing > 0
    screen = vertices @ basis.T
    triangles = screen[faces[keep]]
    order = np.argsort(triangles[:, :, 2].mean(axis=1))  # far to near
    triangles = triangles[order]
    shade = (0.35 + 0.65 * np.clip(facing[keep][order], 0.0, 1.0))[:, None]
    if face_colors is None:
        base = np.full((len(order), 3), 0.82)
    else:
        base = np.asarray(face_colors)[keep][order][:, :3] / 255.0
    colors = np.clip(base * shade, 0.0, 1.0)

    figure = _new_figure(*size_in)
    figure.set_dpi(dpi)
    axes = figure.add_subplot()
    collection = PolyCollection(
        triangles[:, :, :2], facecolors=colors, edgecolors=colors, linewidths=0.1, antialiased=False
    )
    axes.add_collection(collection)
    if len(triangles):
        low, high = (
            triangles[:, :, :2].reshape(-1, 2).min(0),
            triangles[:, :, :2].reshape(-1, 2).max(0),
        )
        axes.set_xlim(low[0], high[0])
        axes.set_ylim(low[1], high[1])
    axes.set_aspect("equal")
    axes.set_axis_off()
    if colorbar is not None:
        label, max_value = colorbar
        mappable = ScalarMappable(norm=Normalize(0.0, max_value), cmap=colormaps["jet"])
        figure.colorbar(mappable, ax=axes, shrink=0.7, label=label)
    if title:
        axes.set_title(title, fontsize=9)
    figure.set_dpi(dpi)
    return palette_png(save_png(figure, path))


def palette_png(path: Path, colors: int = 256) -> Path:
    """Re-save a PNG with a palette of ``colors`` (a third of the size for shaded renders)."""
    from PIL import Image

    with Image.open(path) as image:
        small = image.convert("RGB").quantize(colors=colors)
    with atomic_path(path) as tmp:
        small.save(tmp, format="PNG", optimize=True)
    return path
