"""``python -m slam.fleet`` on a real local Ray with 2 CPUs (started once for this module).

One module fixture does everything the tests read: the serial path (three short windows of the
generated room run one after the other in this process, then ``slam.merge``; every run reads the
same cached sequence), then a fleet of the same three windows and a recording whose root is
missing, run as a subprocess that joins this module's Ray with
``--address``, interrupted with SIGINT once one run finished, and continued in this process.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from slam.app import fleet_cli, fleet_ray
from slam.app.fleet_manifest import FleetRun, Sweep, load_manifest
from slam.app.fleet_plan import merge_levels, run_argv, run_memory_mb, thread_share
from slam.app.fleet_sweep import metric_row, sweep_csv
from slam.run_folder.outputs import read_run_status
from tests.helpers import call_main, popen_interruptible

ray = pytest.importorskip("ray")

ROOT = Path(__file__).resolve().parents[1]
# the 60-frame lap of the generated room that tests/test_rerun_logger.py and test_eval.py read
# from the default cache, with ground-truth odometry (a 6-degree step per frame); three windows
# that overlap by 8 frames, so each shares places with the next; coarse depth, map and mesh to
# keep each run to seconds; one thread, so a run is bitwise reproducible (test_determinism.py)
SETTINGS = {
    "generated.num_frames": 60,
    "submaps.max_frames": 10,
    "source.depth.stride": 4,
    "mapping.voxel_size_m": 0.2,
    "mapping.mesh_subdivisions": 2,
    "output.mesh_samples": 0,
    "threads": 1,
}
WINDOWS = {"a": "0:24", "b": "16:40", "c": "32:56"}


def _set_args(**overrides) -> list[str]:
    settings = {**SETTINGS, **overrides}
    return [arg for key, value in settings.items() for arg in ("--set", f"{key}={value}")]


def _serial(base: Path) -> None:
    """The serial path in this process: each window's ``slam.run``, then ``slam.merge``."""
    from slam.app.cli import main
    from slam.app.merge_cli import main as merge

    for name, frames in WINDOWS.items():
        argv = ["demo", "--odometry", "gt", "--frames", frames, "--no-viz", "--no-progress"]
        result = call_main(main, [*argv, "--out", str(base / name), *_set_args()])
        assert result.returncode == 0, result.stderr[-2000:]
    runs = [str(base / name) for name in WINDOWS]
    result = call_main(merge, [*runs, "--out", str(base / "merged"), "--no-viz"])
    assert result.returncode == 0, result.stderr[-2000:]


def _python(*args: str) -> subprocess.Popen:
    """``python ARGS``, which SIGINT interrupts however pytest was started."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return popen_interruptible(
        [sys.executable, *args], cwd=ROOT, env=env, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip


def _finished(folder: Path) -> bool:
    status = read_run_status(folder) if folder.is_dir() else None
    return status is not None and status.get("state") == "finished"


@pytest.fixture(scope="module")
def ray_address():
    """A local Ray the fleet commands join. ``ray.init`` installs a SIGTERM handler of its own
    and ``ray.shutdown`` leaves it: put back this worker's, or every later test here would fork
    children that survive SIGTERM."""
    sigterm = signal.getsignal(signal.SIGTERM)
    ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR", log_to_driver=False)
    signal.signal(signal.SIGTERM, sigterm)
    yield ray.get_runtime_context().gcs_address
    ray.shutdown()
    signal.signal(signal.SIGTERM, sigterm)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory, ray_address) -> dict:
    base = tmp_path_factory.mktemp("fleet")
    _serial(base / "serial")

    entries = [
        {"name": name, "dataset": "demo", "odometry": "gt", "frames": frames, "set": SETTINGS}
        for name, frames in WINDOWS.items()
    ]
    entries.append({"name": "broken", "dataset": "kitti", "sequence": "00", "root": "missing"})
    manifest = base / "fleet.yaml"
    manifest.write_text(yaml.safe_dump(entries, sort_keys=False))
    out = base / "out"

    first = _python("-m", "slam.fleet", str(manifest), "--out", str(out),
                    "--address", ray_address, "--no-progress")  # fmt: skip
    deadline = time.monotonic() + 300
    while not any(_finished(out / "runs" / name) for name in WINDOWS):
        assert first.poll() is None, first.communicate()
        assert time.monotonic() < deadline, "no run finished within 300 s"
        time.sleep(0.2)
    done_before = {
        name: (out / "runs" / name / "map.npz").stat()
        for name in WINDOWS
        if _finished(out / "runs" / name)
    }
    first.send_signal(signal.SIGINT)
    _, first_err = first.communicate(timeout=120)
    after_interrupt = {name: read_run_status(out / "runs" / name) for name in [*WINDOWS, "broken"]}

    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        resumed = fleet_cli.main([str(manifest), "--out", str(out), "--no-progress"])
    return {
        "base": base,
        "out": out,
        "manifest": manifest,
        "interrupted": (first.returncode, first_err),
        "done_before": done_before,
        "after_interrupt": after_interrupt,
        "resumed": (resumed, stdout.getvalue(), stderr.getvalue()),
    }


def test_fleet_map_equals_the_serial_path(fleet):
    out, serial = fleet["out"], fleet["base"] / "serial"
    for name in WINDOWS:
        assert (out / "runs" / name / "poses_slam.kitti.txt").read_bytes() == (
            serial / name / "poses_slam.kitti.txt"
        ).read_bytes(), name
    merged = (out / "merged" / "poses_slam.kitti.txt").read_bytes()
    assert merged == (serial / "merged" / "poses_slam.kitti.txt").read_bytes()
    rows = (out / "merged" / "sessions.csv").read_text().splitlines()[1:]
    assert [row.split(",")[1] for row in rows] == [str(out / "runs" / n) for n in WINDOWS]
    metrics = json.loads((out / "merged" / "metrics.json").read_text())
    assert metrics["inter_session_loops_kept"] >= 2  # each window joined to the next


def test_a_broken_recording_is_reported_and_the_others_merged(fleet):
    code, stdout, stderr = fleet["resumed"]
    assert code == 1
    log = fleet["out"] / "logs" / "broken.log"
    errors = [line for line in stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, stderr
    assert errors[0].startswith("error: run broken failed: dataset root ") and str(log) in errors[0]
    assert "does not exist" in log.read_text()
    assert "3 of 4 runs finished, 1 failed" in stdout
    assert (fleet["out"] / "merged" / "map.npz").is_file()


def test_an_interrupted_fleet_stops_cleanly_and_resumes_without_recomputing(fleet):
    code, stderr = fleet["interrupted"]
    assert code == 130, stderr[-4000:]
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert lines[-1].startswith("error: interrupted; finished runs are kept in "), stderr
    done_before, states = fleet["done_before"], fleet["after_interrupt"]
    assert done_before and len(done_before) < len(WINDOWS)  # something was left to do
    for name in WINDOWS:
        if name not in done_before and states[name] is not None:  # stopped, not killed
            assert states[name]["state"] in ("interrupted", "finished"), states[name]
    _, _, resumed_err = fleet["resumed"]
    for name, before in done_before.items():
        after = (fleet["out"] / "runs" / name / "map.npz").stat()
        assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns), name
        assert f"{name}: finished earlier, reused" in resumed_err
    assert all(_finished(fleet["out"] / "runs" / name) for name in WINDOWS)


def test_a_finished_fleet_is_reused_whole(fleet):
    """Called once more without the broken recording, nothing is run and the merge is kept."""
    merged = (fleet["out"] / "merged" / "map.npz").stat()
    manifest = fleet["base"] / "fixed.yaml"
    entries = yaml.safe_load(fleet["manifest"].read_text())
    manifest.write_text(yaml.safe_dump([e for e in entries if e["name"] != "broken"]))
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = fleet_cli.main([str(manifest), "--out", str(fleet["out"]), "--no-progress"])
    assert code == 0
    assert stdout.getvalue().startswith("3 of 3 runs finished; merged map in ")
    assert stderr.getvalue().count("finished earlier, reused") == 3
    assert "holds these runs already, reused" in stderr.getvalue()
    again = (fleet["out"] / "merged" / "map.npz").stat()
    assert (again.st_ino, again.st_mtime_ns) == (merged.st_ino, merged.st_mtime_ns)


def test_sweep_rows_read_each_runs_metrics(fleet):
    sweep = Sweep.model_validate(
        {"run": {"name": "s", "dataset": "demo"}, "grid": {"threads": [1, 2], "x.y": [True]}}
    )
    combos = sweep.combinations()
    assert [(run.name, values) for run, values in combos] == [
        ("s-0", {"threads": 1, "x.y": True}),
        ("s-1", {"threads": 2, "x.y": True}),
    ]
    assert "x.y=true" in run_argv(combos[0][0], Path("o"), 2, record=False)
    folder = fleet["out"] / "runs" / "a"
    row = metric_row(folder, finished=True)
    metrics = json.loads((folder / "metrics.json").read_text())
    assert row["ate_rmse_m"] == metrics["trajectory"]["slam"]["ate_rmse_m"]
    assert row["map_npz_bytes"] == (folder / "map.npz").stat().st_size
    text = sweep_csv([("s-0", combos[0][1], row), ("s-1", combos[1][1], {"state": "failed"})],
                     list(sweep.grid))  # fmt: skip
    header, first, failed = text.splitlines()
    assert header.startswith("run,threads,x.y,state,ate_rmse_m,ate_x_rmse_m")
    assert first.startswith("s-0,1,True,finished,")
    assert failed == "s-1,2,True,failed" + "," * (len(header.split(",")) - 4)


def test_a_task_interrupts_itself_when_the_stop_file_appears(tmp_path: Path):
    """The fleet stops its tasks through a file (a ``ray.cancel``-ed task that then returns can
    abort the driver inside Ray): a run in a task stops as on Ctrl-C once the file appears, and
    a task that has not started yet returns at once without a run folder."""
    stop, out = tmp_path / ".stop", tmp_path / "run"
    argv = ["demo", "--odometry", "gt", "--no-viz", "--no-progress", "--out", str(out),
            *_set_args(**{"generated.num_frames": 400})]  # fmt: skip
    snippet = (
        "import sys\nfrom slam.app.fleet_ray import call_logged\n"
        f"sys.exit(call_logged('slam.app.cli', {argv!r}, {str(tmp_path / 'log')!r}, "
        f"{str(stop)!r})[0])"
    )
    child = _python("-c", snippet)
    deadline = time.monotonic() + 120
    while ((read_run_status(out) if out.is_dir() else None) or {}).get("frames_done", 0) < 1:
        assert child.poll() is None, child.communicate()
        assert time.monotonic() < deadline, "no frame done within 120 s"
        time.sleep(0.1)
    stop.touch()
    child.communicate(timeout=120)
    assert child.returncode == 130, (tmp_path / "log").read_text()[-2000:]
    assert read_run_status(out)["state"] == "interrupted"
    assert fleet_ray.call_logged("slam.app.cli", argv, str(tmp_path / "log2"), str(stop)) == (
        130,
        "stopped before it started",
    )
    assert not (tmp_path / "log2").exists()


def test_a_bad_manifest_is_one_line_naming_the_file_and_entry(tmp_path: Path):
    manifest = tmp_path / "m.yaml"
    manifest.write_text("- {name: a, dataset: demo}\n- {name: b, dataset: demo, frame: '0:9'}\n")
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
        code = fleet_cli.main([str(manifest), "--out", str(tmp_path / "out")])
    assert code == 1
    assert stderr.getvalue() == (
        f"error: {manifest}: entry 2 (name 'b'): unknown key 'frame'; did you mean 'frames'?\n"
    )
    assert not (tmp_path / "out").exists()
    manifest.write_text("- {name: a, dataset: demo}\n- {name: a, dataset: nope}\n")
    with pytest.raises(Exception, match="entry 2 \\(name 'a'\\): invalid value 'nope'"):
        load_manifest(manifest)


def test_without_ray_the_command_says_how_to_install_it(tmp_path: Path, monkeypatch):
    manifest = tmp_path / "m.yaml"
    manifest.write_text("- {name: a, dataset: demo}\n")
    monkeypatch.setitem(sys.modules, "ray", None)
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
        code = fleet_cli.main([str(manifest), "--out", str(tmp_path / "out")])
    assert code == 2
    assert stderr.getvalue() == (
        'error: the fleet runs on Ray, which is not installed; pip install -e ".[ray]"\n'
    )


def test_merge_tree_order_cpu_share_and_memory_of_a_task():
    folders = [Path(f"r{k}") for k in range(5)]
    levels = merge_levels(folders, Path("o"), tree=True)
    assert [[step.inputs for step in level] for level in levels] == [
        [folders[0:2], folders[2:4]],
        [[Path("o/merge_tree/level1-0"), Path("o/merge_tree/level1-1")]],
        [[Path("o/merge_tree/level2-0"), folders[4]]],
    ]
    assert levels[-1][0].out == Path("o/merged") and levels[-1][0].runs == folders
    assert [len(level) for level in merge_levels(folders, Path("o"), tree=False)] == [1]
    assert thread_share(2, 2, 3) == 1 and thread_share(16, 16, 1) == 16
    assert thread_share(256, 16, 100) == 2 and thread_share(256, 16, 4) == 16
    demo = {"name": "a", "dataset": "demo"}
    unscored = FleetRun.model_validate({**demo, "set": {"output": {"mesh_samples": 0}}})
    assert run_memory_mb(unscored) < run_memory_mb(FleetRun.model_validate(demo))
    assert run_memory_mb(FleetRun.model_validate({"name": "k", "dataset": "kitti"})) >= 1000
