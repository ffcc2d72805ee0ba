"""Fixtures shared by several test files.

Run folders that take tens of seconds to make (a short demo run with and without a recording, a
short generated-LiDAR run, two sessions of one room and their merge) are made once per test
session, in this process (``slam.app.cli.main``), not by a new interpreter: with pytest-xdist the
first worker that needs one makes it under a file lock in a folder that all workers of the
session share; the others wait for it and reuse it. Tests only read these folders (a test that
changes one copies it first).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.helpers import (
    DEMO_ARGS,
    LIDAR_ARGS,
    ROOM_INSIDE_FRAMES,
    ROOM_SESSION_ARGS,
    ROOM_SESSION_FRAMES,
    CommandResult,
    call_main,
    seeded_prior,
    sphere_points,
)


@pytest.fixture(scope="session", autouse=True)
def _one_thread_per_pool() -> None:
    """Every native pool (torch's OpenMP, OpenCV, BLAS) on one thread in each test process.

    Their idle threads spin: next to the other pytest worker, a pool of two threads on two cores
    waits a time slice whenever one of its threads is descheduled. A short room run through the
    pipeline took 5.4 s alone and 96.6 s beside one busy process with torch on two threads,
    against 7.0 s on one. Commands run in a test set their own pools (``slam.assembly.threads``)."""
    from slam.assembly.threads import apply_plan, plan_thread_budget

    apply_plan(plan_thread_budget(1, map_worker=False))


@pytest.fixture(autouse=True)
def _pools_on_one_thread() -> None:
    """Torch and OpenCV back to one thread before each test: a command a test ran in this
    process sets both from its budget (``slam.assembly.threads``) and must not leave its setting
    to the next test. BLAS needs no reset: every budget gives it one thread."""
    import cv2

    torch.set_num_threads(1)
    cv2.setNumThreads(1)


@pytest.fixture(scope="session")
def shared_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder shared by every pytest-xdist worker of this session (the worker's own base
    folder without xdist)."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # pytest-N/popen-gwK: pytest-N is the session's
    folder = base / "shared"
    folder.mkdir(exist_ok=True)
    return folder


def built_once(shared_dir: Path, name: str, build: Callable[[Path], None]) -> Path:
    """``shared_dir/name``, made by ``build(folder)`` by the first worker that asks for it; the
    others wait on its lock. A build that failed is retried by the next caller."""
    from filelock import FileLock  # comes with torch

    folder = shared_dir / name
    done = shared_dir / f"{name}.done"
    with FileLock(str(shared_dir / f"{name}.lock")):
        if not done.exists():
            if folder.exists():
                shutil.rmtree(folder)
            build(folder)
            done.touch()
    return folder


def run_slam(*argv: str) -> CommandResult:
    """``python -m slam.run ARGV`` in this process; a failed run fails the test."""
    from slam.app.cli import main

    result = call_main(main, list(argv))
    assert result.returncode == 0, result.stderr[-3000:]
    return result


@pytest.fixture(scope="session")
def demo_run(shared_dir: Path) -> Path:
    """Run folder of the short demo (:data:`DEMO_ARGS`) with ``--rrd`` (``recording.rrd``),
    extracting every mesh the recording asks for during the run (no time share: on a run this
    short the share would pay for none)."""

    def build(folder: Path) -> None:
        recording = ("--rrd", str(folder / "recording.rrd"), "--set", "viz.mesh_time_share=1")
        run_slam(*DEMO_ARGS, *recording, "--out", str(folder))

    return built_once(shared_dir, "demo-rrd", build)


@pytest.fixture(scope="session")
def demo_run_without_viewer(shared_dir: Path) -> Path:
    """Run folder of the same short demo with ``--no-viz``, its mesh not scored (what a test
    compares with :func:`demo_run` are the poses and loops)."""

    def build(folder: Path) -> None:
        run_slam(*DEMO_ARGS, "--no-viz", "--set", "output.mesh_samples=0", "--out", str(folder))

    return built_once(shared_dir, "demo-no-viz", build)


@dataclass(frozen=True)
class FinishedRun:
    folder: Path
    result: CommandResult


@pytest.fixture(scope="session")
def lidar_run(shared_dir: Path) -> FinishedRun:
    """A short generated-LiDAR run (:data:`LIDAR_ARGS`): its folder and what it printed."""

    def build(folder: Path) -> None:
        result = run_slam(*LIDAR_ARGS, "--out", str(folder))
        (shared_dir / "lidar-run.stdout").write_text(result.stdout)
        (shared_dir / "lidar-run.stderr").write_text(result.stderr)

    folder = built_once(shared_dir, "lidar-run", build)
    printed = CommandResult(
        0,
        (shared_dir / "lidar-run.stdout").read_text(),
        (shared_dir / "lidar-run.stderr").read_text(),
    )
    return FinishedRun(folder, printed)


def _drop_first_frames(data: Path, count: int) -> None:
    """Delete the images of the first ``count`` frames of the generated room and their rows in
    its lists."""
    (room,) = data.glob("*/room")
    rows = (room / "associations.txt").read_text().splitlines()
    for row in rows[:count]:
        for name in row.split()[1::2]:
            (room / name).unlink()
    (room / "associations.txt").write_text("\n".join(rows[count:]) + "\n")
    for name in ("rgb.txt", "depth.txt"):
        lines = (room / name).read_text().splitlines()
        header = [line for line in lines if line.startswith("#")]
        body = [line for line in lines if not line.startswith("#")]
        (room / name).write_text("\n".join(header + body[count:]) + "\n")


def _room_session(
    folder: Path, data: Path, frames: str | None, *extra: str, record: bool = False
) -> Path:
    frame_args = ("--frames", frames) if frames else ()
    viz = ("--rrd", str(folder / "recording.rrd")) if record else ("--no-viz",)
    run_slam(
        "demo", "--root", str(data), *frame_args, *viz, "--no-progress",
        "--out", str(folder), *ROOM_SESSION_ARGS, *extra,
    )  # fmt: skip
    return folder


@pytest.fixture(scope="session")
def room_sessions(shared_dir: Path) -> dict[str, Path]:
    """Two sessions of one generated room that share a place, and their merge.

    ``a``: the first half of a lap; ``continued``: the second half continuing ``a``'s map
    (``--map``) after the first half's images were deleted, its run alone in ``b``
    (``continued/session``); ``merged``: ``python -m slam.merge a b`` afterwards, with the
    merge's stdout and stderr beside it (``merged.stdout``, ``merged.stderr``); ``localised``:
    the second half localised in ``a``'s map (``--map a --localise``); ``inside``: frames
    20-49, which start in the middle of ``a``, localised in ``a``'s map with a recording
    (``inside/recording.rrd``). Also ``coarse`` (another voxel size) and ``other`` (a stretch
    ``a`` never saw). Every image is deleted before the merge: a merge must never need the
    scans."""

    def build(base: Path) -> None:
        from slam.app.merge_cli import main as merge_main

        data = base / "data"
        half = ROOM_SESSION_FRAMES
        a = _room_session(base / "a", data, f"0:{half}")
        _room_session(base / "coarse", data, "0:10", "--set", "mapping.voxel_size_m=0.15")
        _room_session(base / "other", data, "80:90")
        localise_in_a = ("--map", str(a), "--localise")
        _room_session(base / "inside", data, ROOM_INSIDE_FRAMES, *localise_in_a, record=True)
        _drop_first_frames(data, half)  # the continuation cannot read the first run's scans
        continued = _room_session(base / "continued", data, None, "--map", str(a))
        _room_session(base / "localised", data, None, *localise_in_a)
        shutil.rmtree(data)
        merged = base / "merged"
        result = call_main(merge_main, [str(a), str(continued / "session"), "--out", str(merged)])
        assert result.returncode == 0, result.stderr
        (base / "merged.stdout").write_text(result.stdout)
        (base / "merged.stderr").write_text(result.stderr)

    base = built_once(shared_dir, "room-sessions", build)
    names = ("a", "coarse", "other", "continued", "merged", "localised", "inside")
    return {name: base / name for name in names} | {"b": base / "continued" / "session"}


@pytest.fixture()
def saved_map(tmp_path: Path):
    """A small neural map saved to ``map.npz``: three sphere submaps, two fused, two moved (one
    never fused). Returns ``(map, submaps, path)``."""
    from mapping.config import MapConfig
    from mapping.map_io import save_map
    from mapping.neural_map import NeuralMap

    cfg = MapConfig(min_points_per_voxel=1, min_weight_to_decode=1.0, device="cpu")
    nm = NeuralMap(cfg, seeded_prior())
    subs = []
    for i, centre in enumerate([(0, 0, 0), (0.25, 0.1, 0), (0.5, 0.0, 0.1)]):
        p, n = sphere_points(1500, centre, i)
        subs.append(nm.encode(10 + i, p, n, np.eye(4)))
    nm.fuse(subs[0])
    nm.fuse(subs[1])
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T[:3, 3] = [0.0123, -0.0456, 0.078]
    nm.move(subs[1], T)
    nm.move(subs[2], T)  # never fused
    path = tmp_path / "map.npz"
    save_map(nm, path, subs)
    return nm, subs, path


LONGEST_FIRST = (
    "test_fleet.py",
    "test_localise.py",
    "test_merge.py",
    "test_eval.py",
    "test_determinism.py",
    "test_rerun_logger.py",
    "test_command_errors.py",
    "test_untrusted_maps.py",
    "test_pipeline.py",
    "test_odometry.py",
    "test_loop_closure.py",
    "test_cli.py",
    "test_faults.py",
    "test_lidar_recordings.py",
    "test_loop_ambiguity.py",
)
"""Test files that take longest on 2 cores (``pytest --durations``), longest first. `make test`
hands whole files to its two workers in collection order (``--dist loadfile
--no-loadscope-reorder``): starting with these leaves short files for the end, so both workers
finish together instead of one waiting on a long file started last."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
