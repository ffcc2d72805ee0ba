"""Plain helpers shared by several test files (fixtures live in ``tests/conftest.py``)."""

from __future__ import annotations

import contextlib
import io
import itertools
import json
import logging
import os
import signal
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from slam.run_folder.trajectory_io import read_kitti, read_tum

if TYPE_CHECKING:
    import trimesh

# A short demo: one lap of the generated room in 60 frames with ground-truth odometry (so that a
# 6-degree step per frame is no problem), small submaps so that the lap closes a loop and the map
# is meshed several times, and a coarse mesh lattice to keep it fast.
DEMO_ARGS = [
    "demo", "--odometry", "gt", "--set", "generated.num_frames=60",
    "--set", "submaps.max_frames=10", "--set", "source.depth.stride=4",
    "--set", "mapping.mesh_subdivisions=2", "--set", "output.mesh_samples=20000", "--no-progress",
]  # fmt: skip
# 30 scans of the generated street with 8 m submaps: several submaps in a few seconds; the mesh
# is not scored (no test reads the score, and scoring the street took three times the run).
LIDAR_ARGS = [
    "generated-lidar", "--frames", "0:30", "--no-viz", "--no-progress",
    "--set", "submaps.max_distance_m=8", "--set", "submaps.max_map_points=2000",
    "--set", "output.mesh_samples=0",
]  # fmt: skip
# A short lap of a generated room (its end revisits its start), split in two sessions; the runs
# do not score their meshes (no test reads the scores) and mesh on a 5 cm lattice (the default
# 2.5 cm one took half of each run's time).
ROOM_SESSION_ARGS = [
    "--set", "generated.num_frames=120", "--set", "output.mesh_samples=0",
    "--set", "mapping.mesh_subdivisions=2",
]  # fmt: skip
ROOM_SESSION_FRAMES = 60
ROOM_INSIDE_FRAMES = "20:50"  # a stretch in the middle of the first session


@dataclass(frozen=True)
class CommandResult:
    """Exit status and output of a command's ``main`` called in this process."""

    returncode: int
    stdout: str
    stderr: str


def call_main(main: Callable[[list[str]], int], argv: list[str]) -> CommandResult:
    """``main(argv)`` of a command (``slam.app.cli.main``, ``slam.app.merge_cli.main``, ...) in
    this process, as ``python -m`` would run it, without the seconds of a new interpreter and its
    imports.

    stdout and stderr are captured; the root logger starts without handlers, as in a new process
    (so the command's own logging set-up decides what reaches stderr), and its handlers and level
    are put back afterwards (a run opens ``run.log`` on the root logger). A run also sets torch's
    threads: the tests' fixtures put those back before the next test."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    for handler in handlers:
        root.removeHandler(handler)
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            status = main(argv)
    finally:
        for handler in list(root.handlers):
            root.removeHandler(handler)
            handler.close()
        for handler in handlers:
            root.addHandler(handler)
        root.setLevel(level)
    return CommandResult(status, out.getvalue(), err.getvalue())


def assert_error_line(result: CommandResult, *needles: str) -> str:
    """The command (a :class:`CommandResult` or a ``subprocess.CompletedProcess``) failed with
    exactly one ``error: ...`` line on stderr holding every needle; returns that line."""
    assert result.returncode != 0
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert lines[0].startswith("error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def sphere_points(n: int, centre, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random points on a sphere of radius 0.3 m around ``centre``, and their normals."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * 0.3 + np.asarray(centre), d


def written_before_version_5(
    path: Path, out: Path, version: int, submaps, session: bool = True
) -> None:
    """``path``'s map written at ``out`` as a version 2 to 4 file lays it out: the ``submaps``'
    absolute keys instead of steps between them, no latent scales (float latents only), and
    without its session section unless ``session``."""
    dropped = ("key_deltas", "latent_scales")
    with np.load(path, allow_pickle=False) as npz:
        arrays = {
            k: npz[k]
            for k in npz.files
            if k not in dropped and (session or not k.startswith("session_"))
        }
    header = json.loads(str(arrays["header"]))
    if not session:
        header.pop("session", None)
    arrays["header"] = np.array(json.dumps({**header, "version": version}))
    arrays["keys"] = np.concatenate([s.original.keys.cpu().numpy() for s in submaps])
    np.savez_compressed(out, **arrays)


def seeded_prior(seed: int = 0):
    """A randomly initialised prior model (eval mode), the same for the same seed."""
    from mapping.networks import PriorModel

    torch.manual_seed(seed)
    return PriorModel().eval()


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_pixels(path) -> np.ndarray:
    """The RGB pixels (uint8) of the PNG at ``path``."""
    from matplotlib import image

    with open(path, "rb") as stream:
        assert stream.read(8) == PNG_SIGNATURE, path
    return (image.imread(path)[..., :3] * 255).round().astype(np.uint8)


def figure_pixels(figure) -> np.ndarray:
    """The RGB pixels (uint8) of a matplotlib figure drawn on its Agg canvas."""
    figure.canvas.draw()
    return np.asarray(figure.canvas.buffer_rgba())[..., :3].copy()


def assert_png_shows(path, figure) -> None:
    """The PNG at ``path`` is ``figure``, pixel for pixel (a figure drawn from the data the
    plot should show: any other data, style or layout changes pixels)."""
    np.testing.assert_array_equal(png_pixels(path), figure_pixels(figure))


def colour_mask(pixels: np.ndarray, colour, tolerance: int = 24) -> np.ndarray:
    """Where ``pixels`` (H, W, 3 uint8) are within ``tolerance`` of a matplotlib colour."""
    from matplotlib.colors import to_rgb

    target = np.round(np.asarray(to_rgb(colour)) * 255)
    return np.abs(pixels.astype(int) - target).max(axis=-1) <= tolerance


def one_line(text: str) -> str:
    """The one non-blank line of ``text`` (a traceback or a second line fails)."""
    lines = [line for line in text.splitlines() if line.strip()]
    assert len(lines) == 1, text
    assert "Traceback" not in text
    return lines[0]


def mount_tmpfs(folder: Path, size: str, read_only: bool = False) -> bool:
    """Mount a tmpfs of ``size`` at ``folder`` (root only); False where that is not possible."""
    folder.mkdir(parents=True, exist_ok=True)
    options = f"size={size}" + (",ro" if read_only else "")
    if os.geteuid() != 0:
        return False
    result = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], capture_output=True
    )
    return result.returncode == 0


def umount(folder: Path) -> None:
    """Undo :func:`mount_tmpfs`."""
    subprocess.run(["umount", str(folder)], capture_output=True)


def positions_along(points, step_m: float, height_m: float) -> np.ndarray:
    """(N, 3) positions every ``step_m`` or less along the polyline through the x-y ``points``
    (its ends included), at height ``height_m``."""
    corners = np.asarray(points, dtype=float)
    parts = []
    for a, b in itertools.pairwise(corners):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step_m)))
        parts.append(a + np.linspace(0, 1, n, endpoint=False)[:, None] * (b - a))
    xy = np.concatenate([*parts, corners[-1:]])
    return np.column_stack([xy, np.full(len(xy), height_m)])


def assert_trajectories_complete(folder: Path) -> int:
    """The four trajectory files hold the same frames, TUM timestamps strictly increasing; their
    row count."""
    rows = {len(read_kitti(folder / f"poses_{k}.kitti.txt")) for k in ("odometry", "slam")}
    stamps = [read_tum(folder / f"poses_{k}.tum.txt")[0] for k in ("odometry", "slam")]
    assert len(rows) == 1 and len(stamps[0]) == len(stamps[1]) == rows.pop() > 0
    np.testing.assert_array_equal(stamps[0], stamps[1])
    assert np.all(np.diff(stamps[0]) > 0)
    return len(stamps[0])


@contextlib.contextmanager
def python_sigint():
    """Python's own SIGINT handler (a ``KeyboardInterrupt``) for the block, however pytest was
    started: a shell starts a background job (``pytest &``) with SIGINT ignored. A handled
    signal is reset to its default in a child at exec, so a child started in the block gets
    SIGINT at its default too, where it would have inherited the ignored one."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def popen_interruptible(command: list[str], **kwargs) -> subprocess.Popen:
    """``subprocess.Popen(command, **kwargs)`` for a child the test interrupts with SIGINT
    (:func:`python_sigint`)."""
    with python_sigint():
        return subprocess.Popen(command, **kwargs)


class MeshDistance:
    """Exact point-to-mesh distance, searching the faces of the k nearest dense surface samples
    (trimesh is imported here, not by every test process through conftest)."""

    def __init__(self, mesh: trimesh.Trimesh, spacing_m: float = 0.25) -> None:
        import trimesh
        from scipy.spatial import cKDTree

        count = int(min(mesh.area / spacing_m**2, 2_000_000))
        samples, self._faces = trimesh.sample.sample_surface(mesh, count, seed=0)
        self._tree = cKDTree(samples)
        self._mesh = mesh
        self._closest_point = trimesh.triangles.closest_point

    def __call__(self, points: np.ndarray, k: int = 6) -> np.ndarray:
        _, idx = self._tree.query(points, k=k)
        triangles = self._mesh.triangles[self._faces[idx].ravel()]
        repeated = np.repeat(points, k, axis=0)
        closest = self._closest_point(triangles, repeated)
        return np.linalg.norm(closest - repeated, axis=1).reshape(-1, k).min(axis=1)


def mesh_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    return MeshDistance(mesh)(points)
