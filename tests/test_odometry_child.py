"""The odometry in a child process (frontends/odometry/child_process.py): the same results as in
this process (to the last digits), its errors raised here, large frames, and a clear error when
the child is gone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from frontends.errors import DatasetError, OdometryProcessError
from frontends.frame import Frame
from frontends.odometry import make_odometry
from frontends.odometry.child_process import (
    INITIAL_BYTES,
    ChildProcessOdometry,
    child_process_available,
)
from frontends.odometry.kiss import KissIcpConfig, KissIcpOdometry

pytestmark = pytest.mark.skipif(
    not child_process_available(), reason="the odometry child process needs Linux"
)

ONE_THREAD = KissIcpConfig(registration={"max_num_threads": 1})
POSE_TOLERANCE = 1e-9
"""KISS-ICP fixes TBB's thread limit once per process, at its first registration: where an earlier
test in this process registered on all cores, this process's reductions are not bitwise
reproducible (last digits, ~1e-13), while the child's, on one thread, are."""


def _street(num_frames: int):
    from frontends.sources import make_source

    return make_source("generated", kind="lidar", num_frames=num_frames, azimuth_steps=512)


def _with_times(frame: Frame) -> Frame:
    """The frame with per-point times, so that KISS-ICP deskews it and returns its points."""
    times = np.linspace(0.0, 1.0, len(frame.points))
    return Frame(frame.index, frame.timestamp, frame.points, point_times=times)


def test_child_gives_the_same_poses_and_points_as_in_process() -> None:
    frames = [_with_times(frame) for frame in list(_street(186))[:25]]
    here = make_odometry("kiss-icp", config=ONE_THREAD)
    child = ChildProcessOdometry("kiss-icp", config=ONE_THREAD)
    try:
        for frame in frames:
            expected, got = here.register(frame), child.register(frame)
            np.testing.assert_allclose(got.T_W_S, expected.T_W_S, rtol=0, atol=POSE_TOLERANCE)
            assert got.points is not None and got.points.shape == expected.points.shape
            np.testing.assert_allclose(got.points, expected.points, rtol=0, atol=POSE_TOLERANCE)
            got.points[0, 0] += 1.0  # the caller owns (and may change) the arrays
        assert not np.allclose(got.T_W_S, np.eye(4))  # it did move
    finally:
        child.close()


def test_child_raises_the_odometrys_own_errors() -> None:
    child = ChildProcessOdometry("kiss-icp")
    try:
        with pytest.raises(DatasetError, match="frame 3: empty scan"):
            child.register(Frame(3, 0.0, np.zeros((0, 3))))
        with pytest.raises(DatasetError, match="point times"):
            child.register(Frame(5, 0.0, np.ones((10, 3)), point_times=np.zeros(3)))
    finally:
        child.close()
    with pytest.raises(ValueError, match="max_rnge"):
        ChildProcessOdometry("kiss-icp", data={"max_rnge": 1.0})


def test_frames_larger_than_the_shared_files_cross_both_ways() -> None:
    rng = np.random.default_rng(0)
    num_points = INITIAL_BYTES // 24 + 50_000  # float64 (N, 3): more than the first file size
    directions = rng.normal(size=(num_points, 3))
    points = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    points *= rng.uniform(5.0, 40.0, size=(num_points, 1))
    frame = _with_times(Frame(0, 0.0, points))
    child = ChildProcessOdometry("kiss-icp")
    try:
        result = child.register(frame)
    finally:
        child.close()
    assert result.points is not None and result.points.nbytes > INITIAL_BYTES
    expected = KissIcpOdometry().register(frame).points
    np.testing.assert_allclose(result.points, expected, rtol=0, atol=POSE_TOLERANCE)


def test_a_vanished_child_is_a_clear_error() -> None:
    child = ChildProcessOdometry("kiss-icp")
    os.kill(child.pid, signal.SIGKILL)
    with pytest.raises(RuntimeError, match="kiss-icp odometry process ended"):
        child.register(Frame(0, 0.0, np.ones((10, 3))))
    child.close()
    with pytest.raises(RuntimeError, match="was closed"):
        child.register(Frame(0, 0.0, np.ones((10, 3))))


def test_lidar_runs_put_kiss_icp_in_a_child_that_finish_ends() -> None:
    from slam.algorithm.pipeline import SlamPipeline
    from slam.assembly.builders import build_map, build_odometry
    from slam.assembly.config import RunConfig

    cfg = RunConfig.model_validate({"mapping": {"device": "cpu"}})
    odometry = build_odometry(cfg, "lidar")
    assert isinstance(odometry, ChildProcessOdometry)
    pipeline = SlamPipeline(cfg.pipeline_config(), "lidar", odometry, build_map(cfg))
    for frame in list(_street(186))[:5]:
        pipeline.process(frame)
    pipeline.finish()
    assert odometry.exit_code == 0  # ended, cleanly
    assert len(pipeline.slam_poses()) == 5
    for off in ({"odometry": {"child_process": False}}, {"map_worker": False}):
        inline = build_odometry(RunConfig.model_validate(off), "lidar")
        assert isinstance(inline, KissIcpOdometry)


def test_a_runs_cpu_time_counts_the_childs_registrations_but_not_its_start() -> None:
    """``timing.pipeline_cpu_s`` (slam/app/runner.py ``run_cpu_s``): read once the child runs
    and again after it ended, it holds this process's CPU time and the child's over the frames
    and its exit, not the child's start (importing KISS-ICP), which came before the first
    reading."""
    import resource

    from slam.app.runner import run_cpu_s

    def own_cpu_s() -> float:
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return usage.ru_utime + usage.ru_stime

    frames = list(_street(186))[:8]
    child = ChildProcessOdometry("kiss-icp", config=ONE_THREAD)
    started_s = child.usage().cpu_s
    start, own_start = run_cpu_s(child), own_cpu_s()
    for frame in frames:
        child.register(frame)
    registered_s = child.usage().cpu_s - started_s
    own_s = own_cpu_s() - own_start
    child.close()
    counted_s = run_cpu_s(None) - start
    assert registered_s > 0
    # the child's exit (about 0.15 s) is counted too; its start (about 1 s) is not
    assert registered_s + own_s - 0.05 <= counted_s < registered_s + own_s + started_s / 2


def test_a_hung_child_is_stopped_after_the_reply_timeout() -> None:
    child = ChildProcessOdometry("kiss-icp")
    child.reply_timeout_s = 1.0  # after starting it, which takes longer on a loaded machine
    os.kill(child.pid, signal.SIGSTOP)  # alive, but never answers
    start = time.monotonic()
    with pytest.raises(OdometryProcessError, match="no reply to 'register' within 1 s"):
        child.register(Frame(0, 0.0, np.ones((10, 3))))
    assert time.monotonic() - start < 10.0
    assert child.exit_code == -signal.SIGKILL
    child.close()


def _parent_script(body: str) -> list[str]:
    return [sys.executable, "-c", textwrap.dedent(body)]


ROOT = Path(__file__).resolve().parents[1]


def test_the_child_dies_with_its_parent() -> None:
    parent = subprocess.Popen(
        _parent_script(
            """
            import sys
            from frontends.odometry.child_process import ChildProcessOdometry
            child = ChildProcessOdometry("gt")
            print(child.pid, flush=True)
            sys.stdin.read()
            """
        ),
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    child_pid = int(parent.stdout.readline())
    parent.kill()  # no cleanup runs: only the kernel can end the child now
    parent.wait()
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and _running(child_pid):
        time.sleep(0.05)
    assert not _running(child_pid)


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_a_parent_that_hangs_up_mid_call_leaves_no_traceback_from_the_child() -> None:
    """What Ctrl-C of a LiDAR run does: the parent closes the socket while the child registers;
    the child's reply finds nobody and it exits quietly."""
    result = subprocess.run(
        _parent_script(
            """
            import numpy as np
            from frontends.frame import Frame
            from frontends.odometry.child_process import ChildProcessOdometry
            child = ChildProcessOdometry("kiss-icp")
            points = np.random.default_rng(0).uniform(-30.0, 30.0, (200_000, 3))
            child._channel.send(("register", Frame(0, 0.0, points)))
            child._channel.conn.close()
            print(child._process.wait(timeout=60))
            """
        ),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.stdout.strip() == "0", result.stderr
    assert "Traceback" not in result.stderr and "BrokenPipe" not in result.stderr
