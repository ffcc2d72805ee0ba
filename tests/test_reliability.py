"""Every bad input, environment error and viewer setting that used to look valid or
end in a traceback, reproduced on generated data in ``tmp_path`` (the fault-injection runs are
in ``tests/test_faults.py``)."""

from __future__ import annotations

import json
import os
import stat
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.harness.net import free_port, listening_addresses
from common.atomic_io import atomic_path, write_text_atomic
from frontends.errors import DatasetError
from frontends.sources import make_source
from mapping.errors import MapFileError, WeightsFileError
from mapping.map_io import load_map
from mapping.networks import PriorModel
from slam.app import cli
from slam.assembly.config import set_overrides
from slam.evaluation.cli import EvalError, evaluate_run
from slam.evaluation.cli import main as eval_main
from tests.dataset_files import make_tum, write_depth, write_rgb
from tests.helpers import call_main, mount_tmpfs, one_line, seeded_prior, umount


def run_cli(argv: list[str], capsys) -> tuple[int, str]:
    status = cli.main(argv)
    err = capsys.readouterr().err.strip()
    return status, err


# -- atomic writes (defects 7, 14) --------------------------------------------------------------


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_atomic_writes_respect_the_umask_like_open(tmp_path: Path, umask: int) -> None:
    old = os.umask(umask)
    try:
        write_text_atomic(tmp_path / "a.txt", "x")
        with atomic_path(tmp_path / "b.npz") as tmp:
            np.savez_compressed(tmp, a=np.zeros(3))
        (tmp_path / "c.txt").write_text("x")
    finally:
        os.umask(old)
    expected = stat.S_IMODE((tmp_path / "c.txt").stat().st_mode)
    assert expected == 0o666 & ~umask
    for name in ("a.txt", "b.npz"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == expected, name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.npz", "c.txt"]


def test_atomic_write_fsyncs_file_and_folder_before_it_is_visible(tmp_path: Path) -> None:
    """strace-free check: os.fsync is called on the file, then on its folder."""
    calls: list[str] = []
    real_fsync = os.fsync

    def spy(fd: int) -> None:
        calls.append("dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        real_fsync(fd)

    os.fsync = spy
    try:
        write_text_atomic(tmp_path / "x.txt", "hello")
    finally:
        os.fsync = real_fsync
    assert calls == ["file", "dir"]
    assert (tmp_path / "x.txt").read_text() == "hello"


def test_failed_atomic_write_leaves_no_temporary(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError), atomic_path(tmp_path / "x.bin") as tmp:
        tmp.write_bytes(b"partial")
        raise RuntimeError("writer failed")
    assert list(tmp_path.iterdir()) == []


# -- map and weights files (defects 2, 4) -------------------------------------------------------


def _flip_inside_member(path: Path, out: Path, member: str) -> None:
    """Flip 16 bytes at the start of a member's compressed data (the zip directory stays)."""
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as z:
        info = z.getinfo(member)
    offset = info.header_offset
    name_len, extra_len = struct.unpack("<HH", data[offset + 26 : offset + 30])
    start = offset + 30 + name_len + extra_len + 2  # the deflate block header: zlib.error
    for i in range(16):
        data[start + i] ^= 0xFF
    out.write_bytes(bytes(data))


def test_corrupted_compressed_member_is_a_map_file_error(saved_map, tmp_path: Path) -> None:
    _, _, path = saved_map
    bad = tmp_path / "flipped.npz"
    _flip_inside_member(path, bad, "latent_coeffs.npy")
    with pytest.raises(MapFileError, match=r"flipped\.npz") as info:
        load_map(bad, seeded_prior())
    assert "\n" not in str(info.value)


def test_foreign_or_corrupt_weights_are_one_line_and_never_suggest_unsafe_loading(
    tmp_path: Path,
) -> None:
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(os.urandom(4096))
    foreign = tmp_path / "foreign.pt"
    torch.save({"format": "neural-remap-slam/prior", "obj": Path("x")}, foreign)
    for path in (garbage, foreign):
        with pytest.raises(WeightsFileError) as info:
            PriorModel.load(path)
        text = str(info.value)
        assert str(path) in text and "\n" not in text
        assert "weights_only" not in text
        assert info.value.__cause__ is None and info.value.__suppress_context__


# -- command line (defects 4, 10, 11, 14) -------------------------------------------------------


def test_negative_frame_range_is_explained(capsys) -> None:
    status, err = run_cli(["demo", "--frames", "-5:10"], capsys)
    assert status == 2
    assert "must not be negative" in one_line(err)


def test_set_frame_range_is_a_range_not_a_base_60_number(capsys) -> None:
    assert set_overrides(["source.frames=10:5"]) == {"source": {"frames": "10:5"}}
    assert set_overrides(["source.frames=0:20:2"]) == {"source": {"frames": "0:20:2"}}
    status, err = run_cli(["demo", "--set", "source.frames=10:5"], capsys)
    assert status == 2
    assert "B must be greater than A" in one_line(err)
    assert one_line(err).startswith("error: --set source.frames=10:5 ")


def test_set_validation_error_names_the_set_argument(capsys) -> None:
    status, err = run_cli(["demo", "--set", "submaps.max_frames=abc"], capsys)
    assert status == 1
    line = one_line(err)
    assert "--set submaps.max_frames=abc" in line
    assert "configs/" not in line


def test_out_that_cannot_be_created_names_out(capsys) -> None:
    status, err = run_cli(["demo", "--out", "/proc/x", "--no-viz"], capsys)
    assert status == 2
    assert one_line(err).startswith("error: --out /proc/x: cannot create")


def test_output_root_pointing_at_a_file_names_output_root(tmp_path: Path, capsys) -> None:
    afile = tmp_path / "afile"
    afile.write_text("")
    status, err = run_cli(["demo", "--no-viz", "--set", f"output.root={afile}"], capsys)
    assert status == 2
    assert f"output.root {afile}" in one_line(err)


def test_read_only_out_is_one_line(tmp_path: Path, capsys) -> None:
    folder = tmp_path / "ro"
    if not mount_tmpfs(folder, "1m", read_only=True):
        pytest.skip("needs root and tmpfs mounts to make a read-only folder (root ignores modes)")
    try:
        status, err = run_cli(["demo", "--no-viz", "--out", str(folder)], capsys)
    finally:
        umount(folder)
    assert status == 2
    assert "cannot write in this folder" in one_line(err)


# -- garbage input (defect 3) -------------------------------------------------------------------


def test_folder_of_truncated_scans_fails_instead_of_an_empty_success(tmp_path: Path) -> None:
    scans = tmp_path / "scans"
    scans.mkdir()
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 1000\n"
    header += "property float x\nproperty float y\nproperty float z\nend_header\n"
    for i in range(3):
        (scans / f"{i:06d}.ply").write_bytes(header.encode() + b"\0" * 30)  # 2.5 of 1000 points
    out = tmp_path / "run"
    result = call_main(cli.main, [
        "lidar", str(scans), "--dataloader", "generic", "--no-viz", "--no-progress",
        "--out", str(out),
    ])  # fmt: skip
    assert result.returncode == 1, result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    assert not (out / "metrics.json").exists()


# -- RGB-D folders (defects 8, 9, 12) -----------------------------------------------------------


def test_rgb_and_depth_count_mismatch_warns(tmp_path: Path, caplog) -> None:
    make_tum(tmp_path / "seq")  # 4 colour images, 5 depth images (one far in time)
    with caplog.at_level("WARNING"):
        source = make_source("tum", root=tmp_path, sequence="seq")
    assert len(source) == 4
    assert any("1 frames dropped" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("entry", ["../outside.png", "/etc/passwd"])
def test_list_entries_leaving_the_folder_are_refused(tmp_path: Path, entry: str) -> None:
    folder = tmp_path / "seq"
    make_tum(folder)
    write_rgb(tmp_path / "outside.png")
    lines = (folder / "rgb.txt").read_text().splitlines()
    lines[1] = f"{lines[1].split()[0]} {entry}"
    (folder / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError) as info:
        make_source("tum", root=tmp_path, sequence="seq")
    assert "leaves the dataset folder" in str(info.value) and "\n" not in str(info.value)
    if entry.startswith(".."):
        source = make_source("tum", root=tmp_path, sequence="seq", allow_outside_paths=True)
        assert len(source) == 4


def test_missing_intrinsics_warns_and_zero_depth_scale_is_refused(tmp_path: Path, caplog) -> None:
    folder = tmp_path / "my_camera"
    make_tum(folder)
    with caplog.at_level("WARNING"):
        make_source("tum", root=tmp_path, sequence="my_camera")
    assert any("no intrinsics.txt" in r.getMessage() for r in caplog.records)
    (folder / "intrinsics.txt").write_text("525 525 319.5 239.5 640 480 0\n")
    with pytest.raises(DatasetError) as info:
        make_source("tum", root=tmp_path, sequence="my_camera")
    assert "intrinsics.txt" in str(info.value) and "positive" in str(info.value)
    write_depth(folder / "depth" / "x.png", np.ones((4, 4)), 5000)  # keeps the helper in use


# -- slam.eval (defects 5, 13) ------------------------------------------------------------------


def _fake_run(folder: Path) -> None:
    folder.mkdir()
    rows = [f"{i}.0 {i * 0.1} 0 0 0 0 0 1" for i in range(5)]
    for kind in ("slam", "odometry"):
        (folder / f"poses_{kind}.tum.txt").write_text("\n".join(rows) + "\n")


def test_eval_of_an_interrupted_run_fails_and_writes_nothing(tmp_path: Path) -> None:
    run = tmp_path / "run"
    _fake_run(run)
    (run / "run_status.json").write_text(
        json.dumps({"state": "interrupted", "frames_done": 7, "frames_total": 40})
    )
    with pytest.raises(EvalError, match="interrupted at frame 7 of 40"):
        evaluate_run(run, make_plots=False)
    (run / "run_status.json").write_text(
        json.dumps({"state": "running", "frames_done": 3, "frames_total": 40})
    )
    with pytest.raises(EvalError, match="did not finish"):
        evaluate_run(run, make_plots=False)
    assert not (run / "metrics.json").exists()
    result = call_main(eval_main, [str(run), "--no-plots"])
    assert result.returncode == 1
    assert "did not finish" in one_line(result.stderr)


def test_eval_names_the_malformed_tum_file(tmp_path: Path) -> None:
    run = tmp_path / "run"
    _fake_run(run)
    (run / "poses_slam.tum.txt").write_text("1.0 garbage\n")
    with pytest.raises(DatasetError, match=r"poses_slam\.tum\.txt"):
        evaluate_run(run, make_plots=False)


# -- --serve (defect 1) -------------------------------------------------------------------------


def test_serve_binds_both_servers_to_the_configured_loopback_address(tmp_path: Path) -> None:
    if not Path("/proc/net/tcp").exists():
        pytest.skip("needs /proc/net/tcp to list listening sockets")
    from slam.app.rerun_logger import RerunLogger

    grpc_port, web_port = free_port(), free_port()
    logger = RerunLogger(
        rrd_path=tmp_path / "r.rrd",
        serve_port=grpc_port,
        web_port=web_port,
        serve_bind_ip="127.0.0.1",
    )
    try:
        assert logger.viewer_url.startswith(f"http://127.0.0.1:{web_port}/")
        assert listening_addresses(web_port) == {"127.0.0.1"}
        assert listening_addresses(grpc_port) == {"127.0.0.1"}
    finally:
        logger.close()
    assert listening_addresses(web_port) == set()


FORK_AFTER_HANDLING_SIGTERM = """
import os, signal, sys
from slam.app.signals import handle_sigterm
handle_sigterm()
pid = os.fork()
if pid == 0:  # the forked child: is SIGTERM's default back?
    os._exit(0 if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL else 1)
_, status = os.waitpid(pid, 0)
sys.exit(os.waitstatus_to_exitcode(status))
"""


def test_sigterm_handler_is_scoped_to_main_and_not_inherited_by_forks(capsys) -> None:
    """A forked worker must keep SIGTERM's default (a stuck worker could not run the Python
    handler, and a pool's terminate() would then hang), and main() restores the handler. The
    fork happens in a new interpreter: forking this one, with the threads of earlier tests,
    could deadlock the child."""
    import signal

    before = signal.getsignal(signal.SIGTERM)
    run_cli(["demo", "--frames", "-1:2"], capsys)
    assert signal.getsignal(signal.SIGTERM) is before
    forked = subprocess.run(
        [sys.executable, "-c", FORK_AFTER_HANDLING_SIGTERM],
        capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=60,
    )  # fmt: skip
    assert forked.returncode == 0, forked.stderr
