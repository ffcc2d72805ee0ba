"""``python -m slam.run``: bad input ends in one clear line; a short run writes its folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from slam.app.cli import UsageError, main, parse_frames
from tests.helpers import CommandResult, assert_error_line, call_main, popen_interruptible

ROOT = Path(__file__).resolve().parents[1]


def run_cli(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """``python -m slam.run ARGS`` in a new interpreter: for what only the real process shows
    (its exit status, signals, the web viewer)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-m", "slam.run", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def slam_run(*args: str) -> CommandResult:
    """``python -m slam.run ARGS`` in this process (``slam.app.cli.main``)."""
    return call_main(main, list(args))


def test_unknown_dataset():
    """The real command: one line on stderr and exit status 2."""
    result = run_cli("kitty", "00")
    assert_error_line(result, "unknown dataset 'kitty'", "kitti")
    assert result.returncode == 2


def test_missing_root(tmp_path: Path):
    assert_error_line(slam_run("kitti", "00"), "--root")
    missing = tmp_path / "nowhere"
    assert_error_line(slam_run("kitti", "00", "--root", str(missing)), str(missing))


def test_root_without_the_sequence(tmp_path: Path):
    assert_error_line(
        slam_run(
            "kitti", "00", "--root", str(tmp_path), "--no-viz", "--out", str(tmp_path / "run")
        ),
        "sequences",
    )


def test_bad_frame_range(tmp_path: Path):
    assert_error_line(slam_run("demo", "--frames", "9:3"), "--frames '9:3'")
    assert_error_line(slam_run("demo", "--frames", "a:b"), "integers")


def test_unknown_config_key(tmp_path: Path):
    config = tmp_path / "bad.yaml"
    config.write_text("submaps:\n  max_frame: 20\n")
    result = slam_run("demo", "--config", str(config), "--out", str(tmp_path / "run"))
    assert_error_line(result, "submaps.max_frame", str(config))
    result = slam_run("demo", "--set", "loop_closure.rgbd.radius=2", "--out", str(tmp_path / "r"))
    assert_error_line(result, "loop_closure.rgbd.radius")


def test_parse_frames():
    assert parse_frames("10:50") == slice(10, 50, None)
    assert parse_frames("::3") == slice(None, None, 3)
    for bad in ("5", "1:2:0", "-1:5", "1:2:3:4"):
        with pytest.raises(UsageError):
            parse_frames(bad)


def test_short_run_writes_the_run_folder(lidar_run) -> None:
    """30 frames of the generated street (tests/helpers.py LIDAR_ARGS)."""
    out, result = lidar_run.folder, lidar_run.result
    assert "Traceback" not in result.stderr
    for name in (
        "config.yaml",
        "poses_odometry.kitti.txt",
        "poses_odometry.tum.txt",
        "poses_slam.kitti.txt",
        "poses_slam.tum.txt",
        "loops.csv",
        "mesh.ply",
        "metrics.json",
        "run.log",
    ):
        assert (out / name).is_file(), name
    assert any(out.glob("map*")), list(out.iterdir())
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_frames"] == 30
    assert metrics["num_submaps"] >= 2
    assert metrics["trajectory"]["slam"]["ate_rmse_m"] < 0.5
    assert len((out / "poses_slam.kitti.txt").read_text().splitlines()) == 30
    assert "run folder:" in result.stdout


def test_out_never_mixes_into_or_deletes_a_folder_it_did_not_create(tmp_path: Path):
    # A non-empty folder is refused and left as it was.
    user = tmp_path / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("keep me\n")
    result = slam_run("demo", "--no-viz", "--out", str(user))
    assert_error_line(result, "not empty", str(user))
    assert [p.name for p in user.iterdir()] == ["notes.txt"]
    # An empty folder of the user's is used; a run that fails in it does not delete it.
    empty = tmp_path / "empty"
    empty.mkdir()
    missing = tmp_path / "nowhere.bag"
    result = slam_run("kitti", "00", "--root", str(tmp_path), "--no-viz", "--out", str(empty))
    assert_error_line(result, "sequences")
    assert empty.is_dir()
    # A folder the failed run created itself is removed again.
    created = tmp_path / "new" / "run"
    result = slam_run("kitti", "00", "--root", str(tmp_path), "--no-viz", "--out", str(created))
    assert_error_line(result, "sequences")
    assert not created.exists()
    result = slam_run("lidar", str(missing), "--no-viz", "--out", str(tmp_path / "x"))
    assert_error_line(result, str(missing))


def test_lidar_and_rgbd_need_a_path():
    assert_error_line(slam_run("lidar"), "PATH")
    assert_error_line(slam_run("rgbd"), "PATH")
    assert_error_line(slam_run("demo", "--dataloader", "rosbag"), "lidar dataset only")


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_streams_to_the_web_viewer_and_stops_cleanly(tmp_path: Path):
    import signal
    import socket
    import time
    import urllib.request

    web_port, grpc_port = _free_port(), _free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    command = [
        sys.executable, "-m", "slam.run", "generated-lidar", "--frames", "0:4", "--serve",
        "--no-progress", "--out", str(tmp_path / "run"),
        "--set", f"viz.serve_web_port={web_port}", "--set", f"viz.serve_grpc_port={grpc_port}",
        "--set", "submaps.max_map_points=2000", "--set", "loop_closure.enabled=false",
        "--set", "output.write_map=false", "--set", "viz.mesh_every_submaps=1000",
        "--set", "output.mesh_samples=1000",
    ]  # fmt: skip
    process = popen_interruptible(
        command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        url = None
        for line in process.stderr:
            if line.startswith("viewer: "):
                url = line.split(" ", 1)[1].strip()
            if "still serving" in line:
                break
        assert url is not None and url.startswith(f"http://127.0.0.1:{web_port}/?url=")
        assert f"127.0.0.1%3A{grpc_port}%2Fproxy" in url
        page = urllib.request.urlopen(url, timeout=30).read().decode()
        assert "<html" in page.lower() and "rerun" in page.lower()
        with socket.create_connection(("127.0.0.1", grpc_port), timeout=10):
            pass  # the gRPC server that the page's viewer reads is up
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=300)  # generous: CI may be heavily loaded
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 0, stderr[-2000:]
    assert "Traceback" not in stderr
    assert (tmp_path / "run" / "metrics.json").is_file()
    assert (tmp_path / "run" / "recording.rrd").stat().st_size > 0
    time.sleep(0.5)
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", grpc_port), timeout=2).close()


def test_icl_trajectories_are_written_in_the_release_frame(tmp_path: Path):
    """The five real ICL-NUIM frames in the TUM-compatible release layout (associations.txt with
    depth first, frame-number stamps, livingRoom2.gt.freiburg): a mapping-only run must write
    exactly the release's relative motion, i.e. the trajectory evo compares with the .gt.freiburg
    file, not its y-mirrored copy that the loader works in."""
    import shutil

    import numpy as np

    from frontends.sources._io import read_tum_trajectory

    real = ROOT.parent / "shared" / "data" / "icl_nuim_livingroom_5"
    if not real.is_dir():
        pytest.skip(f"{real} not found (real-data sample)")
    folder = tmp_path / "living_room_traj2_frei_png"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rows = (real / "pose.txt").read_text().split("\n")
    rows = [row for row in rows if row.strip()]
    for n in range(1, 6):
        shutil.copy(real / "color" / f"{n}.png", folder / "rgb" / f"{n}.png")
        shutil.copy(real / "depth" / f"{n}.png", folder / "depth" / f"{n}.png")
    (folder / "associations.txt").write_text(
        "".join(f"{n} depth/{n}.png {n} rgb/{n}.png\n" for n in range(1, 6))
    )
    gt_file = tmp_path / "livingRoom2.gt.freiburg"
    gt_file.write_text("".join(f"{n} {rows[n - 1]}\n" for n in range(1, 6)))
    out = tmp_path / "run"
    result = slam_run(
        "icl", "lr-kt2", "--root", str(tmp_path), "--odometry", "gt", "--no-viz",
        "--no-progress", "--out", str(out), "--set", "source.depth.stride=8",
        "--set", "output.write_map=false", "--set", "mapping.device=cpu",
        "--set", "loop_closure.enabled=false",  # a loop edge would move the ground-truth poses
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    _, written = read_tum_trajectory(out / "poses_slam.tum.txt")
    _, release = read_tum_trajectory(gt_file)
    expected = np.linalg.inv(release[0]) @ release  # gt odometry starts at the identity
    np.testing.assert_allclose(written, expected, atol=1e-5)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["trajectory"]["slam"]["ate_rmse_m"] < 1e-4
    # slam.evaluation.cli against the release file itself (dataset frame) agrees.
    from slam.evaluation.cli import evaluate_run

    evaluated = evaluate_run(out, gt_poses_path=gt_file, make_plots=False, write=False)
    assert evaluated["trajectory"]["slam"]["ate_rmse_m"] < 1e-4


def test_rgbd_image_folder_runs(tmp_path: Path):
    """``python -m slam.run rgbd FOLDER`` on the generated room's folder (rgb/, depth/ with
    rgb.txt/depth.txt, intrinsics.txt, groundtruth.txt)."""
    from frontends.sources import make_source

    room = make_source("generated", kind="rgbd", num_frames=240, seed=0, width=320, height=240)
    out = tmp_path / "run"
    result = slam_run(
        "rgbd", str(room.sequence_dir), "--frames", "0:12", "--no-viz", "--no-progress",
        "--out", str(out), "--set", "source.depth.stride=4", "--set", "output.write_map=false",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_frames"] == 12 and metrics["trajectory"]["frames_scored"] == 12
    assert metrics["trajectory"]["slam"]["ate_rmse_m"] < 0.004  # measured: 0.14 cm
