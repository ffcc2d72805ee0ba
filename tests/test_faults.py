"""Fault injection: SIGINT, SIGTERM and SIGKILL at several points of a short demo run,
and SIGTERM during an atomic map-sized write. Afterwards every file present must be complete and
loadable, no temporary file may remain (SIGKILL aside: nothing can clean up after it, but every
visible file is still complete), and ``slam.eval`` must refuse the partial run.

Each run is a few seconds of processing on the shared generated demo sequence (generated once
into the default cache); the module takes about a minute on two cores.
"""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from mapping.map_io import load_map
from slam.assembly.config import load_run_config
from slam.run_folder.trajectory_io import read_kitti, read_tum
from tests.helpers import assert_trajectories_complete, call_main, popen_interruptible

REPO_ROOT = Path(__file__).resolve().parents[1]
RUN_FRAMES = 120
"""Long enough that a signal sent when the first submap closes (frame 5) lands mid-run even
on a loaded machine; a run stopped early never reads the rest."""
RUN_ARGS = [
    "demo",
    "--frames",
    f"0:{RUN_FRAMES}",
    "--no-progress",
    "--set",
    "submaps.max_frames=5",
    "--set",
    "output.mesh_samples=1000",
]


def _rrd_verifies(path: Path) -> bool:
    import rerun_cli

    binary = Path(rerun_cli.__file__).parent / "rerun"
    result = subprocess.run(
        [str(binary), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120
    )
    return result.returncode == 0


def assert_complete(folder: Path, allow_temporaries: bool = False) -> set[str]:
    """Every file in a run folder loads; returns the names present."""
    names = {p.name for p in folder.iterdir()}
    temporaries = {n for n in names if n.startswith(".")}
    if not allow_temporaries:
        assert not temporaries, temporaries
    for name in names - temporaries:
        path = folder / name
        if name.endswith(".tum.txt"):
            assert len(read_tum(path)[1]) > 0
        elif name.endswith(".kitti.txt"):
            assert len(read_kitti(path)) > 0
        elif name == "loops.csv":
            with path.open(newline="") as f:
                assert next(csv.reader(f))[0] == "reference_submap"
        elif name == "config.yaml":
            load_run_config(path)
        elif name.endswith(".json"):
            json.loads(path.read_text())
        elif name == "mesh.ply":
            assert len(trimesh.load(path, force="mesh", process=False).faces) > 0
        elif name == "map.npz":
            load_map(path)
        elif name == "recording.rrd" and not allow_temporaries:
            assert _rrd_verifies(path), "recording.rrd has no valid footer"
    return names


def run_until(folder: Path, trigger: str, sig: int) -> subprocess.CompletedProcess:
    """Start a demo run into ``folder``, send ``sig`` once ``trigger`` exists there."""
    process = popen_interruptible(
        [sys.executable, "-m", "slam.run", *RUN_ARGS, "--rrd", str(folder / "recording.rrd"),
         "--out", str(folder)],
        cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    deadline = time.monotonic() + 300
    while not (folder / trigger).exists():
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            out, err = process.communicate()
            pytest.fail(f"run ended before {trigger} appeared: {err[-2000:]}")
        time.sleep(0.02)
    process.send_signal(sig)
    out, err = process.communicate(timeout=120)
    return subprocess.CompletedProcess(process.args, process.returncode, out, err)


def eval_refuses(folder: Path, needle: str) -> None:
    """``slam.eval`` (in this process: its command line is not under test) refuses the run."""
    from slam.evaluation.cli import main as eval_main

    result = call_main(eval_main, [str(folder), "--no-plots"])
    assert result.returncode == 1, result.stderr
    assert needle in result.stderr
    assert not (folder / "metrics.json").exists()


@pytest.mark.parametrize(
    ("sig", "status", "message", "state"),
    [
        (signal.SIGINT, 130, "error: interrupted", "interrupted"),
        (signal.SIGTERM, 143, "error: terminated (SIGTERM)", "terminated"),
    ],
    ids=["sigint", "sigterm"],
)
def test_signal_after_the_first_submap_leaves_complete_files(
    tmp_path: Path, sig: int, status: int, message: str, state: str
) -> None:
    folder = tmp_path / "run"
    result = run_until(folder, "poses_slam.tum.txt", sig)
    assert result.returncode == status, result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    assert message in result.stderr
    names = assert_complete(folder)
    assert {"poses_slam.tum.txt", "recording.rrd", "run_status.json"} <= names
    run_status = json.loads((folder / "run_status.json").read_text())
    assert run_status["state"] == state and 0 < run_status["frames_done"] < RUN_FRAMES
    # whole trajectory files, no frame the status does not count
    assert assert_trajectories_complete(folder) <= run_status["frames_done"]
    eval_refuses(folder, f"{state} at frame")


def test_a_finished_run_leaves_every_frame_in_its_trajectory_files(lidar_run) -> None:
    """The final trajectory files hold every frame the run processed, in order."""
    status = json.loads((lidar_run.folder / "run_status.json").read_text())
    assert status["state"] == "finished"
    assert assert_trajectories_complete(lidar_run.folder) == status["frames_done"]


def test_sigkill_leaves_only_complete_visible_files(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    result = run_until(folder, "poses_slam.tum.txt", signal.SIGKILL)
    assert result.returncode == -signal.SIGKILL
    assert_complete(folder, allow_temporaries=True)
    eval_refuses(folder, "did not finish")


def test_sigterm_during_a_map_sized_write_leaves_no_file_and_no_temporary(
    tmp_path: Path,
) -> None:
    """The write of ``map.npz`` (``common.atomic_io``) under the run's SIGTERM handler; the
    payload is large enough that the signal arrives while the temporary file is written."""
    script = (
        "import sys, numpy as np\n"
        "from common.atomic_io import atomic_path\n"
        "from slam.app.signals import Terminated, handle_sigterm\n"
        "handle_sigterm()\n"
        "data = np.random.default_rng(0).random(40_000_000).astype(np.float32)\n"
        "print('ready', flush=True)\n"
        "try:\n"
        "    with atomic_path(sys.argv[1]) as tmp, open(tmp, 'wb') as f:\n"
        "        np.savez_compressed(f, latents=data)\n"
        "except Terminated:\n"
        "    sys.exit(143)\n"
    )
    target = tmp_path / "map.npz"
    process = subprocess.Popen(
        [sys.executable, "-c", script, str(target)],
        cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert process.stdout.readline().strip() == "ready"
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".map.npz.*.tmp.npz")):
        assert process.poll() is None and time.monotonic() < deadline, process.stderr.read()
        time.sleep(0.005)
    time.sleep(0.2)  # inside the compression
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 143, err
    assert list(tmp_path.iterdir()) == []


def test_interrupted_final_map_write_keeps_the_previous_complete_map(tmp_path: Path) -> None:
    """A finished map survives a second, interrupted save over it (KeyboardInterrupt raised by
    the writer itself: the same path as Ctrl-C at that moment)."""
    from common.atomic_io import atomic_path

    target = tmp_path / "map.npz"
    np.savez_compressed(target, a=np.arange(10))
    with pytest.raises(KeyboardInterrupt), atomic_path(target) as tmp:
        with open(tmp, "wb") as f:
            f.write(b"PK\x03\x04 half")
        raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.npz"]
    with np.load(target) as npz:
        assert npz["a"].tolist() == list(range(10))
