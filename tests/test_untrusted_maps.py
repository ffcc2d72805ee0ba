"""A map file from elsewhere is untrusted input: a corpus of crafted ``map.npz`` files, each made
from one small real map (``save_map`` of a tiny NeuralMap with a session section), must end in
one line naming the file, with nothing written, quickly and in little memory.

Size bombs (a member inflating far beyond its declared size, an ``.npy`` header claiming 10^12
elements, arrays consistent with each other but far larger than the file), header lies (meshing
and voxel size out of bounds, a weights file or device chosen by the file, deep JSON nesting) and
broken sessions (NaN anchors, an edge to an unknown anchor, descriptors of another width, short
timestamps, NaN descriptors, malformed parts). Most cases load in this process (time and
``tracemalloc`` peak measured); a few run ``slam.merge`` as a user would, in parallel, their
own peak RSS measured (``MeasuredCommand``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from benchmarks.harness.child import MeasuredCommand
from benchmarks.harness.crafted_maps import CRAFTED, header_edit, rewritten
from common.atomic_folder import FolderBusyError, atomic_folder
from mapping.config import MapConfig
from mapping.errors import MapFileError
from mapping.map_io import load_map, save_map
from mapping.networks import load_default_prior
from mapping.neural_map import NeuralMap
from slam.algorithm.loops.place import PlaceDescriptor
from slam.algorithm.merge.merge import MergeError, merge_sessions
from slam.algorithm.merge.session import Edge, SessionRecord
from slam.app.merge_cli import load_run
from slam.evaluation.cli import evaluate_run, summary_lines
from slam.run_folder.trajectory_io import write_kitti, write_tum

ROOT = Path(__file__).resolve().parents[1]
MAX_SECONDS = 30.0
MAX_BYTES = 1 << 30
ANCHORS = (3, 7, 9)
FRAMES = 30


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def _session(rng: np.random.Generator, sensor: str = "rgbd") -> SessionRecord:
    cov = np.diag(np.full(6, 1e-4))
    return SessionRecord(
        setup={"sensor": sensor, "dataset": "test", "session_id": "a" * 32},
        node_ids=np.array(ANCHORS),
        T_W_A=np.array([_pose(0.25 * k) for k in range(len(ANCHORS))]),
        odometry=[Edge(3, 7, _pose(0.25), cov), Edge(7, 9, _pose(0.25), cov)],
        loops=[],
        frame_submap=np.repeat(ANCHORS, FRAMES // len(ANCHORS)),
        frame_T_A_S=np.tile(np.eye(4), (FRAMES, 1, 1)),
        timestamps=100.0 + np.arange(FRAMES) / 30.0,
        descriptors={
            n: PlaceDescriptor(
                rng.uniform(-1, 1, (20, 3)).astype(np.float32),
                rng.integers(0, 256, (20, 32), dtype=np.uint8),
                False,
            )
            for n in ANCHORS
        },
    )


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    """A run folder holding one small real map with a session (three submaps of spheres)."""
    folder = tmp_path_factory.mktemp("untrusted") / "good"
    folder.mkdir()
    rng = np.random.default_rng(0)
    cfg = MapConfig(min_points_per_voxel=1, min_weight_to_decode=1.0, device="cpu")
    neural_map = NeuralMap(cfg, load_default_prior())
    submaps = []
    for k, n in enumerate(ANCHORS):
        d = rng.normal(size=(1500, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        submap = neural_map.encode(n, d * 0.3, d, _pose(0.25 * k))
        neural_map.fuse(submap)
        submaps.append(submap)
    save_map(neural_map, folder / "map.npz", submaps, session=_session(rng).to_arrays())
    return folder


INFLATED = "size: member inflating past its declared size"
CORPUS = {
    "size: member inflating past its declared size": "inconsistent",
    "size: npy header claiming 10^12 elements": "inconsistent",
    "size: consistent arrays far larger than the file": "crafted",
    "header: mesh_subdivisions 200": "mesh_subdivisions",
    "header: voxel size inf": "voxel_size_m",
    "header: voxel size 1e-9": "voxel_size_m",
    "header: encoder_table_nodes 10^6": "table",
    "header: deep JSON nesting": "corrupt map header",
    "arrays: latent scales of rank 2": "array 'latent_scales' has shape",
    "arrays: a zero latent scale": "latent_scales must be positive",
    "arrays: key steps going back": "keys must be sorted",
    "session: NaN anchors": "anchor poses",
    "session: edge to an unknown anchor": "unknown",
    "session: descriptors 16 bytes wide": "descriptor_bits",
    "session: short timestamps": "timestamps",
    "session: NaN descriptor positions": "descriptor positions",
    "session: malformed parts": "parts",
}
"""Every crafted map of :data:`CRAFTED` and what its one-line error must name."""


def _crafted(good: Path, out: Path, craft) -> Path:
    """A run folder holding ``good``'s map crafted by ``craft``."""
    out.mkdir()
    craft(good / "map.npz", out / "map.npz")
    return out


@pytest.mark.parametrize("case", list(CORPUS))
def test_crafted_map_is_one_line(good: Path, tmp_path: Path, case: str):
    assert set(CORPUS) == set(CRAFTED)
    folder = _crafted(good, tmp_path / "crafted", CRAFTED[case])
    needle = CORPUS[case]
    before = sorted(p.name for p in folder.iterdir())
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(MapFileError) as info:
            load_run(folder)
        seconds = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    message = str(info.value)
    assert "\n" not in message and str(folder / "map.npz") in message, message
    assert needle in message, message
    assert seconds < MAX_SECONDS and peak < MAX_BYTES, (seconds, peak)
    assert sorted(p.name for p in folder.iterdir()) == before  # nothing written


def test_header_chooses_no_file_and_no_device(good: Path, tmp_path: Path):
    """``weights_path: /etc/passwd`` and ``device: cuda`` in a header are ignored: the map loads
    with the reader's prior and device, and the named file is never opened."""
    lies = header_edit(weights_path="/etc/passwd", device="cuda")
    folder = _crafted(good, tmp_path / "lies", lies)
    opened = []

    def audit(event, args):
        if event == "open" and args and "passwd" in str(args[0]):
            opened.append(args[0])

    sys.addaudithook(audit)
    item, neural_map = load_run(folder, MapConfig(device="cpu"))
    assert not opened
    assert neural_map.device.type == "cpu" and neural_map.cfg.weights_path is None
    assert neural_map.num_voxels > 0 and len(item.submaps) == len(ANCHORS)
    # a map made with another prior is refused in one line (the identity is only compared)
    other = _crafted(
        good, tmp_path / "other", rewritten(lambda h, a: h.update(model_identity="f" * 16))
    )
    with pytest.raises(MapFileError, match="same prior weights") as info:
        load_map(other / "map.npz")
    assert "\n" not in str(info.value)


def test_run_merged_with_itself_or_its_part_is_refused(good: Path, tmp_path: Path):
    copy = tmp_path / "copy"
    shutil.copytree(good, copy)
    inputs = [load_run(good), load_run(copy)]
    with pytest.raises(MergeError, match="same session") as info:
        merge_sessions([i for i, _ in inputs], [m for _, m in inputs])
    assert "\n" not in str(info.value)
    # an older file without ids: identical contents are the same session
    old = _crafted(
        good, tmp_path / "old", rewritten(lambda h, a: h["session"]["setup"].pop("session_id"))
    )
    item = load_run(old)
    with pytest.raises(MergeError, match="same session"):
        merge_sessions([item[0], inputs[0][0]], [item[1], inputs[0][1]])
    # a merged run holding this one as a part
    parts = [
        {"name": "x", "first_row": 0, "rows": FRAMES, "session_id": "a" * 32},
    ]

    def merged(header, arrays):
        header["session"]["setup"]["session_id"] = "b" * 32
        header["session"]["parts"] = parts

    whole = load_run(_crafted(good, tmp_path / "merged", rewritten(merged)))
    with pytest.raises(MergeError, match="same session"):
        merge_sessions([whole[0], inputs[0][0]], [whole[1], inputs[0][1]])


def _no_descriptors(header, arrays):
    """A session without place descriptors (its run had loop closure off)."""
    arrays["session_descriptor_ids"] = np.zeros(0, np.int64)
    arrays["session_descriptor_planar"] = np.zeros(0, bool)
    arrays["session_descriptor_offsets"] = np.zeros(1, np.int64)
    arrays["session_descriptor_positions"] = np.zeros((0, 3), np.float16)
    arrays["session_descriptor_bits"] = np.zeros((0, 32), np.uint8)


def test_output_folder_is_claimed_and_appears_whole(tmp_path: Path):
    out = tmp_path / "out"
    with atomic_folder(out) as partial:
        (partial / "a.txt").write_text("a")
        assert not out.exists() and partial.name.startswith(".out.partial-")
        with pytest.raises(FolderBusyError, match="another process"), atomic_folder(out):
            pass  # a second writer is refused while the first holds the claim
    assert (out / "a.txt").read_text() == "a"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    with pytest.raises(FolderBusyError, match="new or empty"), atomic_folder(out):
        pass
    for stop in (KeyboardInterrupt, OSError):
        with pytest.raises(stop), atomic_folder(tmp_path / "failed") as partial:
            (partial / "half.txt").write_text("x")
            raise stop()
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    # a claim left by a killed writer is taken over
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()  # fmt: skip
    (tmp_path / ".late.claim").write_text(dead)
    with atomic_folder(tmp_path / "late") as partial:
        (partial / "b.txt").write_text("b")
    assert (tmp_path / "late" / "b.txt").is_file() and not (tmp_path / ".late.claim").exists()


def test_cli_cases_end_in_one_line(good: Path, tmp_path: Path):
    """A few cases as a user meets them, in parallel: one ``error:`` line, nothing written,
    peak RSS of the command itself under 1 GB. ``--map`` refuses a map of another sensor or
    without place descriptors before reading a frame (its data is never generated)."""
    crafted = {
        "inflated": _crafted(good, tmp_path / "inflated", CRAFTED[INFLATED]),
        "no-descriptors": _crafted(good, tmp_path / "nodesc", rewritten(_no_descriptors)),
    }
    (tmp_path / ".busy.claim").write_text(f"{os.getpid()}\n")  # a live writer holds it
    run = ("slam.run", "--no-viz", "--no-progress", "--root", str(tmp_path / "data"))
    commands = {
        "inflated": ("slam.merge", "--no-viz", str(good), str(crafted["inflated"])),
        "claimed": ("slam.merge", str(good), str(good), "--out", str(tmp_path / "busy")),
        "sensor": (*run, "generated-lidar", "--map", str(good)),
        "no-descriptors": (*run, "demo", "--map", str(crafted["no-descriptors"])),
    }
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    running = {}
    for name, (module, *args) in commands.items():
        if "--out" not in args:
            args += ["--out", str(tmp_path / f"out-{name}")]
        running[name] = MeasuredCommand(
            [sys.executable, "-m", module, *args],
            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
    needles = {"sensor": "sensor", "no-descriptors": "no place descriptors", "claimed": "pid"}
    for name, command in running.items():
        _, stderr = command.process.communicate()
        finished = command.wait()
        lines = [line for line in stderr.splitlines() if line.strip()]
        assert finished.returncode in (1, 2), (name, stderr)
        assert len(lines) == 1 and lines[0].startswith("error: "), (name, stderr)
        assert needles.get(name, "map.npz") in lines[0], (name, lines[0])
        assert finished.peak_rss_mb * 2**20 < MAX_BYTES, (name, finished.peak_rss_mb)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([".busy.claim", *(f.name for f in crafted.values())]), left


def test_eval_reads_a_merged_run(good: Path, tmp_path: Path):
    """A merged run folder (``sessions.csv``, no odometry) is scored for what it has."""
    folder = tmp_path / "merged"
    shutil.copytree(good, folder)
    poses = np.tile(np.eye(4), (FRAMES, 1, 1))
    poses[:, 0, 3] = np.linspace(0, 3, FRAMES)
    truth = poses.copy()
    truth[:, 1, 3] = 0.01
    write_tum(folder / "poses_slam.tum.txt", poses, 100.0 + np.arange(FRAMES) / 30.0)
    write_kitti(folder / "poses_slam.kitti.txt", poses)
    write_kitti(folder / "poses_gt.kitti.txt", truth)
    (folder / "sessions.csv").write_text("session,run_folder,first_row,rows\n0,a,0,30\n")
    metrics = evaluate_run(folder, make_plots=False, write=False)
    assert set(metrics["trajectory"]) >= {"slam"} and "odometry" not in metrics["trajectory"]
    assert metrics["trajectory"]["slam"]["ate_rmse_m"] < 1e-6
    skipped = metrics["evaluation"]["skipped"]
    assert any(s.startswith("odometry") for s in skipped)
    assert any(s.startswith("mesh metrics") for s in skipped)
    assert any(line.startswith("skipped  odometry") for line in summary_lines(metrics))
