"""Bad input and hostile environments for ``slam.run`` and ``slam.eval`` outside map files: each
ends in one ``error:`` line naming the argument or file and the fix, never a traceback, never
an unbounded allocation, and never a silently wrong file."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mapping.errors import WeightsFileError
from mapping.networks import PriorModel
from slam.app import cli
from slam.evaluation import cli as eval_cli
from slam.evaluation.run_metrics import CullDistanceTooSmall, check_cull_distance
from slam.run_folder.outputs import KittiRows, RunOutputs, kitti_rows_filled
from slam.run_folder.trajectory_io import read_kitti, read_tum
from tests.helpers import call_main, mount_tmpfs, one_line, umount

REPO_ROOT = Path(__file__).resolve().parents[1]
SHORT = ["demo", "--frames", "0:3", "--no-progress", "--set", "output.mesh_samples=1000"]


def run_main(argv: list[str], capsys) -> tuple[int, str]:
    status = cli.main(argv)
    return status, capsys.readouterr().err.strip()


def run_eval(argv: list[str], capsys) -> tuple[int, str]:
    try:
        status = eval_cli.main(argv)
    except SystemExit as exc:  # argparse's usage errors
        status = int(exc.code)
    return status, capsys.readouterr().err.strip()


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished 12-frame demo run with a mesh (made once for this file)."""
    folder = tmp_path_factory.mktemp("eval") / "run"
    argv = ["demo", "--frames", "0:12", "--no-viz", "--no-progress",
            "--set", "output.mesh_samples=1000", "--out", str(folder)]  # fmt: skip
    result = call_main(cli.main, argv)
    assert result.returncode == 0, result.stderr[-2000:]
    return folder


def _copy(run: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    return copy


# -- slam.eval ----------------------------------------------------------------------------------


def test_a_tiny_cull_distance_is_refused_before_subdividing() -> None:
    floor = np.array([[[-2, -2, 0], [2, -2, 0], [2, 2, 0]]], dtype=float)
    check_cull_distance(floor, 0.05)  # about 16 k faces
    with pytest.raises(CullDistanceTooSmall, match=r"use at least"):
        check_cull_distance(floor, 1e-4)  # 4**12 faces per face: the unbounded case
    with pytest.raises(CullDistanceTooSmall):
        check_cull_distance(floor, -1.0)


def test_eval_cull_distance_and_samples_are_bounded(finished_run: Path, capsys) -> None:
    for argv in (
        ["--cull-distance-m", "0"],
        ["--cull-distance-m", "-1"],
        ["--samples", "-5"],
        ["--samples", "10000000000"],
        ["--samples", "1e10"],
    ):
        status, err = run_eval([str(finished_run), "--no-plots", *argv], capsys)
        assert status == 2, argv
        assert one_line(err).startswith(f"error: argument {argv[0]}"), err
    status, err = run_eval([str(finished_run), "--no-plots", "--cull-distance-m", "1e-5"], capsys)
    assert status == 1
    assert "--cull-distance-m" in one_line(err) and "use at least" in err


def test_eval_names_a_garbage_or_corrupt_mesh(finished_run: Path, tmp_path: Path, capsys) -> None:
    garbage = tmp_path / "gt.ply"
    garbage.write_bytes(np.random.default_rng(0).bytes(3000))
    status, err = run_eval([str(finished_run), "--no-plots", "--gt-mesh", str(garbage)], capsys)
    assert status == 1 and str(garbage) in one_line(err)
    run = _copy(finished_run, tmp_path)
    (run / "mesh.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9\n")
    status, err = run_eval([str(run), "--no-plots"], capsys)
    assert status == 1 and str(run / "mesh.ply") in one_line(err)


def test_eval_refuses_an_absurd_generated_sequence(
    finished_run: Path, tmp_path: Path, capsys
) -> None:
    run = _copy(finished_run, tmp_path)
    (run / "metrics.json").unlink()
    for name in ("poses_gt.kitti.txt", "poses_gt.tum.txt"):
        (run / name).unlink()  # ground truth must then come from regenerating the sequence
    config = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(config.replace("num_frames: 240", "num_frames: 1000000000"))
    status, err = run_eval([str(run), "--no-plots"], capsys)
    assert status == 1
    assert "generated.num_frames" in one_line(err)


def _read_only_copy(source: Path, target: Path) -> bool:
    target.mkdir(parents=True)
    if os.geteuid() != 0:
        return False
    ok = subprocess.run(["mount", "--bind", str(source), str(target)], capture_output=True)
    if ok.returncode != 0:
        return False
    ro = subprocess.run(["mount", "-o", "remount,ro,bind", str(target)], capture_output=True)
    if ro.returncode != 0:
        umount(target)
        return False
    return True


def test_eval_of_a_read_only_run_or_figures_folder_is_one_line(
    finished_run: Path, tmp_path: Path, capsys
) -> None:
    run = _copy(finished_run, tmp_path)
    mounted = tmp_path / "ro_run"
    if not _read_only_copy(run, mounted):
        pytest.skip("needs root and bind mounts to make a read-only folder (root ignores modes)")
    try:
        status, err = run_eval([str(mounted), "--no-plots"], capsys)
        assert status == 1
        assert f"{mounted}: cannot write in the run folder" in one_line(err)
        status, err = run_eval([str(run), "--figures", str(mounted / "figures")], capsys)
        assert status == 1
        assert f"--figures {mounted / 'figures'}" in one_line(err)
    finally:
        umount(mounted)


# -- config bounds ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "setting",
    [
        "mapping.voxel_size_m=inf",
        "mapping.voxel_size_m=.nan",
        "mapping.voxel_size_m=1e-9",
        "mapping.encoder_table_nodes=1000000",
        "mapping.mesh_subdivisions=100000",
        "threads=1000000000",
        "generated.num_frames=1000000000",
        "submaps.map_voxel_m=1e-9",
        "odometry.kiss_icp.registration.max_num_threads=100000",
    ],
)
def test_config_values_that_size_work_are_bounded(setting: str, tmp_path: Path, capsys) -> None:
    out = tmp_path / "run"
    status, err = run_main([*SHORT, "--no-viz", "--set", setting, "--out", str(out)], capsys)
    assert status == 1
    assert one_line(err).startswith(f"error: --set {setting}: invalid value")
    assert not out.exists()


# -- --serve ------------------------------------------------------------------------------------


def test_web_viewer_dies_with_a_sigkilled_run(tmp_path: Path) -> None:
    if not sys.platform.startswith("linux"):
        pytest.skip("PR_SET_PDEATHSIG is Linux only")
    from benchmarks.harness.net import free_port

    web_port = free_port()
    script = (
        "import sys, time\n"
        "from slam.app.web_viewer import WebViewerServer\n"
        f"server = WebViewerServer('127.0.0.1', {web_port}, 'rerun+http://127.0.0.1:1/proxy')\n"
        "print(server.pid, flush=True)\n"
        "time.sleep(60)\n"
    )
    run = subprocess.Popen(
        [sys.executable, "-c", script], cwd=REPO_ROOT, stdout=subprocess.PIPE, text=True
    )
    try:
        server_pid = int(run.stdout.readline())
    finally:
        run.kill()  # SIGKILL: no Python cleanup runs
        run.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(server_pid, 0)
        except ProcessLookupError:
            break
        with open(f"/proc/{server_pid}/stat") as stat:  # a zombie of init counts as gone
            if stat.read().split(")")[-1].split()[0] == "Z":
                break
        time.sleep(0.1)
    else:
        os.kill(server_pid, signal.SIGKILL)
        pytest.fail("the web viewer outlived the run that started it")


def test_serve_checks_both_ports_and_the_address_first(tmp_path: Path, capsys) -> None:
    from benchmarks.harness.net import free_port

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        out = tmp_path / "run"
        status, err = run_main(
            [*SHORT, "--serve", "--set", f"viz.serve_grpc_port={port}",
             "--set", f"viz.serve_web_port={free_port()}", "--out", str(out)],
            capsys,
        )  # fmt: skip
    assert status == 1
    assert f"viz.serve_grpc_port {port}: already in use" in one_line(err)
    assert not out.exists()
    status, err = run_main(
        [*SHORT, "--serve", "--set", "viz.serve_bind_ip=8.8.8.8", "--out", str(out)], capsys
    )
    assert status == 1
    assert "viz.serve_bind_ip 8.8.8.8: not an address of this machine" in one_line(err)


# -- --rrd --------------------------------------------------------------------------------------


def test_rrd_never_overwrites_and_is_checked_before_the_run_folder(tmp_path: Path, capsys) -> None:
    existing = tmp_path / "old.rrd"
    existing.write_bytes(b"keep me")
    link = tmp_path / "link.rrd"
    link.symlink_to(tmp_path / "elsewhere.rrd")
    out = tmp_path / "run"
    for target, word in ((existing, "exists"), (link, "is a symlink")):
        status, err = run_main([*SHORT, "--rrd", str(target), "--out", str(out)], capsys)
        assert status == 2
        assert one_line(err) == (
            f"error: --rrd {target}: {word}; pass a new file name (a run never overwrites a file)"
        )
    assert existing.read_bytes() == b"keep me" and not link.exists()
    status, err = run_main([*SHORT, "--rrd", "/proc/x/r.rrd", "--out", str(out)], capsys)
    assert status == 2 and one_line(err).startswith("error: --rrd /proc/x/r.rrd: cannot write")
    assert not out.exists()


# -- disk full ----------------------------------------------------------------------------------


def test_disk_full_marks_the_run_failed_and_ends_with_the_error_line(tmp_path: Path) -> None:
    folder = tmp_path / "full"
    if not mount_tmpfs(folder, "160k"):
        pytest.skip("needs root and tmpfs mounts for a size-limited folder")
    out = folder / "out"
    try:
        result = subprocess.run(
            [sys.executable, "-m", "slam.run", "demo", "--frames", "0:6", "--no-progress",
             "--rrd", str(out / "recording.rrd"), "--set", "output.mesh_samples=1000",
             "--set", "viz.flush_timeout_s=2", "--out", str(out)],
            capture_output=True, text=True, cwd=REPO_ROOT, timeout=120,
        )  # fmt: skip
        status = json.loads((out / "run_status.json").read_text())
    finally:
        umount(folder)
    assert result.returncode == 1, result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    # Rerun's own logger reports its file sink's failure too, as the process ends
    rerun_log = re.compile(r"re_[a-z_]+::")
    ours = [line for line in result.stderr.strip().splitlines() if not rerun_log.search(line)]
    errors = [line for line in ours if line.startswith("error: ")]
    assert errors == [ours[-1]], result.stderr
    assert str(out) in errors[0]
    assert "No space left on device" in errors[0] and "free some space" in errors[0]
    assert status["state"] == "failed" and "No space left" in status["reason"]


FULL_DISK_RECORDING = """
import logging, os, sys, time
import numpy as np
import rerun as rr
from slam.app.rerun_flush import exit_process, flush_recording, leave_at_exit_if_given_up
logging.basicConfig(format="%(message)s")
rec = rr.RecordingStream("full-disk")
rec.save(sys.argv[1])
rng = np.random.default_rng(0)
for frame in range(20):  # about 1 MB of points
    rec.set_time("frame", sequence=frame)
    rec.log("points", rr.Points3D(rng.random((5000, 3))))
start = time.monotonic()
written = flush_recording(rec, 1.0, "the full recording")
print(f"written {written} in {time.monotonic() - start:.1f} s", flush=True)
del rec  # the stream stays kept: dropping it would block as its flush did
if sys.argv[2] == "exit_process":
    exit_process(3)  # without Rerun's clean-up at exit, which would block too
leave_at_exit_if_given_up()  # as a Ray worker does: Ray ends its process after the task
sys.exit(3)
"""


@pytest.mark.parametrize("ending", ["exit_process", "interpreter_exit"])
def test_a_recording_its_disk_cannot_take_is_closed_with_a_warning(
    tmp_path: Path, ending: str
) -> None:
    """Rerun's flush waits for ever by default and never returns while its file sink cannot
    write; closing the recording must give up after its timeout and say so, and the process
    must still end: a command with its status, a Ray worker (which ends through the
    interpreter's exit) with 0. In a child: the stuck stream cannot be dropped in this
    process."""
    folder = tmp_path / "full"
    if not mount_tmpfs(folder, "64k"):
        pytest.skip("needs root and tmpfs mounts for a size-limited folder")
    try:
        result = subprocess.run(
            [sys.executable, "-c", FULL_DISK_RECORDING, str(folder / "recording.rrd"), ending],
            capture_output=True, text=True, cwd=REPO_ROOT, timeout=60,
        )  # fmt: skip
    finally:
        umount(folder)
    words = result.stdout.split()
    status = 3 if ending == "exit_process" else 0
    assert result.returncode == status, result.stdout + result.stderr[-2000:]
    assert words[:2] == ["written", "False"], result.stdout + result.stderr[-2000:]
    assert float(words[3]) < 10
    assert "the full recording could not be written completely" in result.stderr


# -- skipped frames -----------------------------------------------------------------------------


def test_kitti_files_keep_one_row_per_scan_when_frames_are_skipped(tmp_path: Path) -> None:
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [1.0, 2.0, 3.0]
    layout = KittiRows(np.array([1, 2, 4]), 6)  # frames 0, 3 and 5 skipped
    filled = kitti_rows_filled(poses, layout)
    np.testing.assert_array_equal(filled[:, 0, 3], [1.0, 1.0, 2.0, 2.0, 3.0, 3.0])
    outputs = RunOutputs(tmp_path)
    outputs.write_poses(poses, poses, np.arange(3.0), layout)
    outputs.write_ground_truth(poses, np.arange(3.0), layout)
    for name in ("poses_odometry", "poses_slam", "poses_gt"):
        assert len(read_kitti(tmp_path / f"{name}.kitti.txt")) == 6, name
        assert len(read_tum(tmp_path / f"{name}.tum.txt")[0]) == 3, name


def test_a_skipped_frame_keeps_the_kitti_rows_aligned_end_to_end(tmp_path: Path, capsys) -> None:
    from tests.dataset_files import make_tum

    folder = tmp_path / "cam"
    make_tum(folder, n=6)
    depth = sorted((folder / "depth").glob("*.png"))[2]  # frame 2: a 40 x 40 pixel patch
    from tests.dataset_files import write_depth

    few = np.zeros((480, 640))
    few[220:260, 300:340] = 1.5
    write_depth(depth, few, 5000)
    out = tmp_path / "run"
    status, err = run_main(
        ["rgbd", str(folder), "--odometry", "gt", "--no-viz", "--no-progress",
         "--set", "output.mesh_samples=0", "--set", "source.min_points=2000",
         "--set", "source.depth.max_depth_m=8",
         "--set", "odometry.rgbd.max_depth_m=8", "--out", str(out)],
        capsys,
    )  # fmt: skip
    assert status == 0, err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["input"]["skipped_frames"] and metrics["input"]["frames_total"] == 6
    slam = read_kitti(out / "poses_slam.kitti.txt")
    assert len(slam) == 6
    skipped = metrics["input"]["skipped_frames"][0]
    np.testing.assert_array_equal(slam[skipped], slam[skipped - 1])
    assert len(read_tum(out / "poses_slam.tum.txt")[0]) == 5


# -- RERUN=off ----------------------------------------------------------------------------------


def test_rerun_off_runs_without_a_recording(tmp_path: Path, capsys, monkeypatch) -> None:
    monkeypatch.setenv("RERUN", "off")
    out = tmp_path / "run"
    status, err = run_main([*SHORT, "--rrd", str(tmp_path / "r.rrd"), "--out", str(out)], capsys)
    assert status == 0, err
    assert "RERUN=off switches Rerun off" in one_line(err)
    assert not (tmp_path / "r.rrd").exists()
    assert json.loads((out / "run_status.json").read_text())["state"] == "finished"


# -- messages -----------------------------------------------------------------------------------


def test_unwritable_cache_names_the_variable(tmp_path: Path, capsys, monkeypatch) -> None:
    cache = tmp_path / "afile"
    cache.write_text("")
    monkeypatch.setenv("NEURAL_REMAP_SLAM_CACHE", str(cache))
    status, err = run_main(
        [*SHORT, "--no-viz", "--set", "generated.num_frames=3", "--out", str(tmp_path / "r")],
        capsys,
    )
    assert status == 1
    assert "NEURAL_REMAP_SLAM_CACHE" in one_line(err) and str(cache) in err


def test_no_usable_frame_names_the_recording(tmp_path: Path, capsys) -> None:
    status, err = run_main(
        [*SHORT, "--no-viz", "--set", "source.min_points=100000000", "--out", str(tmp_path / "r")],
        capsys,
    )
    assert status == 1  # after a warning per skipped frame, the error line
    line = err.splitlines()[-1]
    assert "None" not in line and "generated-rgbd: no usable frame" in line


def test_random_bytes_as_weights_are_not_called_a_pickle(tmp_path: Path) -> None:
    garbage = tmp_path / "prior.pt"
    garbage.write_bytes(np.random.default_rng(1).bytes(4096))
    with pytest.raises(WeightsFileError) as info:
        PriorModel.load(garbage)
    text = str(info.value)
    assert "not the zip archive torch.save writes" in text
    assert "objects other than tensors" not in text and "pickle" not in text
