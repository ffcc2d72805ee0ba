"""The benchmark harness: run_all's list, every benchmark's --quick mode, the report header and
the measured child processes (real processes, no mocks)."""

from __future__ import annotations

import importlib
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import bench_variants, run_all
from benchmarks.harness.child import in_child_measured, run_command
from benchmarks.harness.machine import git_revision, machine_description
from benchmarks.harness.paths import REPO
from benchmarks.harness.reference import kiss_slam_unavailable
from benchmarks.harness.repeat import REPEATS, Timing, repeat_runs, restore_all, timed

BENCH_DIR = Path(run_all.__file__).resolve().parent
ARCHIVE_DIR = REPO / "benchmarks" / "archive"


def test_run_all_lists_exactly_the_benchmark_files():
    present = sorted(p.stem.removeprefix("bench_") for p in BENCH_DIR.glob("bench_*.py"))
    assert sorted(run_all.BENCHMARKS) == present
    assert len(set(run_all.BENCHMARKS)) == len(run_all.BENCHMARKS)
    assert set(run_all.BEFORE_AFTER) <= set(run_all.BENCHMARKS)


@pytest.mark.parametrize("name", run_all.BENCHMARKS)
def test_every_benchmark_imports_and_has_a_quick_mode(name):
    module = importlib.import_module(f"benchmarks.bench_{name}")
    assert module.build_parser().parse_args(["--quick"]).quick is True
    assert callable(module.main)
    if name in run_all.BEFORE_AFTER:
        assert module.build_parser().parse_args(["--before", "HEAD~1"]).before == "HEAD~1"
        assert run_all.bench_command(name, quick=True, before="abc")[-2:] == ["--before", "abc"]
    else:
        assert "--before" not in run_all.bench_command(name, quick=True, before="abc")


def _record(command: str) -> dict:
    return {
        "command": command,
        "invoked_as": "make bench-quick",
        "started": "2026-01-01 10:00 UTC",
        "finished": "2026-01-01 10:12 UTC",
        "total_seconds": 720.0,
        "load_end": "1.0, 1.0, 1.0",
        "mode": "quick",
        "before": None,
        "machine": machine_description(),
        "benchmarks": [
            {
                "name": "odometry",
                "status": "ok",
                "seconds": 12.5,
                "returncode": 0,
                "command": "python -m benchmarks.bench_odometry --quick",
                "detail": "",
            },
            {
                "name": "slam",
                "status": "failed",
                "seconds": 3.0,
                "returncode": 1,
                "command": "python -m benchmarks.bench_slam --quick",
                "detail": "exit status 1\n\nValueError: boom",
            },
        ],
    }


def test_assembled_report_names_command_revision_and_only_this_invocations_sections(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    (results / "odometry.md").write_text("## Odometry\n\n| a | b |\n")
    (results / "prior.md").write_text("## Stale prior section\n")  # not run by this invocation
    output = run_all.assemble(
        _record("python -m benchmarks.run_all --quick"),
        results_dir=results,
        output=tmp_path / "BENCHMARKS.md",
    )
    text = output.read_text()
    header = text.split("| benchmark |")[0]
    assert "`python -m benchmarks.run_all --quick` (via `make bench-quick`)" in header
    assert f"Revision: {git_revision()}" in header
    assert "2026-01-01 10:00 UTC" in header and "cores" in header and "cpu" in header
    assert "## Odometry" in text
    assert "## slam: FAILED" in text and "ValueError: boom" in text
    assert "Stale prior section" not in text


def test_report_links_the_archive_and_inlines_none_of_it(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    (results / "odometry.md").write_text("## Odometry\n")
    text = run_all.assemble(
        _record("python -m benchmarks.run_all --quick"),
        results_dir=results,
        output=tmp_path / "B.md",
    ).read_text()
    history = text.split("## History")[1]
    assert "## Odometry" not in history and "Full-length runs" not in text
    assert "(benchmarks/archive/README.md)" in history
    assert "\n- [" not in history  # the list of runs lives in the archive's index


def test_section_pictures_are_linked_from_the_report_folder(tmp_path):
    results = tmp_path / "benchmarks" / "results"
    results.mkdir(parents=True)
    (results / "corner.png").write_bytes(b"png")
    (results / "odometry.md").write_text(
        "## Odometry\n\n![corner](corner.png) [web](https://x.org/a) [up](#odometry)\n"
    )
    record = _record("python -m benchmarks.run_all --quick")
    output = run_all.assemble(record, results_dir=results, output=tmp_path / "B.md")
    text = output.read_text()
    assert "![corner](benchmarks/results/corner.png)" in text
    assert (output.parent / "benchmarks/results/corner.png").is_file()
    assert "[web](https://x.org/a) [up](#odometry)" in text


def test_archive_index_lists_exactly_the_archived_reports():
    index = (ARCHIVE_DIR / "README.md").read_text()
    listed = re.findall(r"^- \[[^\]]+\]\(([^)]+)\)", index, flags=re.MULTILINE)
    archived = [path.relative_to(ARCHIVE_DIR) for path in ARCHIVE_DIR.rglob("*.md")]
    assert sorted(listed) == sorted(str(p) for p in archived if p.name != "README.md")
    assert len(set(listed)) == len(listed)
    for name in listed:
        assert (ARCHIVE_DIR / name).is_file()


def test_report_over_its_size_limit_is_flagged(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    (results / "odometry.md").write_text("## Odometry\n")
    record = _record("python -m benchmarks.run_all --quick")
    small = run_all.assemble(record, results_dir=results, output=tmp_path / "B.md").read_text()
    assert run_all.check_size(small) is None and "Warning" not in small
    (results / "odometry.md").write_text("## Odometry\n" + "x" * run_all.MAX_REPORT_BYTES)
    large = run_all.assemble(record, results_dir=results, output=tmp_path / "C.md").read_text()
    assert run_all.check_size(large) is not None
    assert large.splitlines()[2].startswith("**Warning: BENCHMARKS.md is")


def test_timings_are_medians_shown_with_their_range():
    timing = Timing([1.0, 3.0, 2.5])
    assert timing == 2.5 and f"{timing:.1f}" == "2.5 (1.0-3.0)"
    assert f"{timing.scaled(1000):.0f}" == "2500 (1000-3000)"
    assert json.loads(json.dumps({"t": timing})) == {"t": 2.5}
    runs = iter([{"wall_s": 2.0, "stage_s": {"a": 1.0}, "ate": 0.1}, {"wall_s": 1.0}])
    calls = []

    def run():
        calls.append(1)
        return next(runs, {"wall_s": 3.0, "stage_s": {"a": 2.0}, "ate": 0.1})

    result = repeat_runs(run, ("wall_s", "stage_s", "fps"), repeats=REPEATS)
    assert len(calls) == REPEATS >= 3 and result["repeats"] == REPEATS
    assert f"{result['wall_s']:.0f}" == "2 (1-3)" and result["ate"] == 0.1
    assert restore_all(json.loads(json.dumps({"run": result})))["run"]["wall_s"] == result["wall_s"]
    skipped = repeat_runs(lambda: calls.append(1) or {"skipped": "no data"}, ("wall_s",))
    assert skipped == {"skipped": "no data"}
    measured = timed(lambda: 7, repeats=3, warmup=True)
    assert measured["result"] == 7 and len(measured["wall_s"].samples) == 3


def test_clear_results_leaves_nothing_from_an_earlier_invocation(tmp_path):
    (tmp_path / "throughput.json").write_text("{}")
    (tmp_path / "slam.md").write_text("old")
    run_all.clear_results(tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_child_function_is_measured_in_its_own_process():
    result, usage = in_child_measured(math.factorial, 12)
    assert result == math.factorial(12)
    assert usage.wall_s > 0 and usage.cpu_s >= 0
    assert 5 < usage.peak_rss_mb < 2000


def test_command_peak_memory_is_the_childs(tmp_path):
    allocate = "b = bytearray(300 * 1024 * 1024); b[::4096] = b'x' * len(b[::4096])"
    run = run_command([sys.executable, "-c", allocate], cwd=tmp_path)
    assert run.returncode == 0
    assert run.usage.peak_rss_mb > 250
    failing = run_command(
        [sys.executable, "-c", "print('said'); raise SystemExit(3)"], cwd=tmp_path
    )
    assert failing.returncode == 3 and "said" in failing.stdout

    with pytest.raises(FileNotFoundError):
        run_command([str(tmp_path / "missing")], cwd=tmp_path)


HOLDING_300_MB = """
import json, math, os, subprocess, sys
from benchmarks.harness.child import in_child_measured, run_command
from benchmarks.harness.reliability import run

held = bytearray(b"x") * (300 << 20)
tiny = [sys.executable, "-c", "import os, time; print(os.getpid()); time.sleep(0.3)"]
plain = subprocess.Popen(tiny, stdout=subprocess.DEVNULL)
_, _, usage = os.wait4(plain.pid, 0)
polled = []
command = run_command(tiny, cwd=".", on_poll=polled.append)
stopped = run_command([sys.executable, "-c", "import time; time.sleep(60)"], cwd=".", timeout_s=0)
print(json.dumps({
    "plain_mb": usage.ru_maxrss / 1024,
    "command_mb": command.usage.peak_rss_mb,
    "reliability_mb": run(".", tiny).peak_rss_mb,
    "function_mb": in_child_measured(math.factorial, 12)[1].peak_rss_mb,
    "printed_pid": int(command.stdout),
    "polled": polled,
    "stopped": [stopped.returncode, stopped.usage.wall_s],
}))
"""
"""A process holding 300 MB measures a tiny command and function. Linux carries the forking
process's high-water mark across exec, so a plain ``wait4`` reports at least 300 MB."""


def test_a_large_parent_measures_a_commands_own_peak_memory():
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    said = subprocess.run(
        [sys.executable, "-c", HOLDING_300_MB], cwd=REPO, env=env, capture_output=True, text=True
    )
    assert said.returncode == 0, said.stderr
    measured = json.loads(said.stdout)
    assert measured["plain_mb"] >= 300
    for key in ("command_mb", "reliability_mb", "function_mb"):
        assert 5 < measured[key] < 150, (key, measured)
    # on_poll samples the command itself, and a timeout kills the command itself
    assert measured["polled"] and set(measured["polled"]) == {measured["printed_pid"]}
    returncode, wall_s = measured["stopped"]
    assert returncode == -9 and wall_s < 10


def test_missing_kiss_slam_environment_gives_a_reason(tmp_path, monkeypatch):
    monkeypatch.setenv("BENCH_KISS_SLAM_VENV", str(tmp_path / "nowhere"))
    reason = kiss_slam_unavailable()
    assert reason is not None
    assert str(tmp_path / "nowhere") in reason and "make kiss-slam-env" in reason


@pytest.mark.parametrize("corrected", [False, True])
def test_kiss_slam_reads_the_scans_as_ours_does(corrected):
    """KISS-SLAM's ``kitti`` dataloader bends every scan by KISS-ICP's KITTI correction; it may
    only be used where our loader applies it too, else the comparison is on other points."""
    from benchmarks.harness.reference import _kiss_slam_input
    from frontends.sources import make_source

    source = make_source(
        "generated",
        kind="lidar",
        num_frames=150,
        seed=0,
        azimuth_steps=1024,
        loader_options={"correct_vertical_angle": corrected},
    )
    args, T_cam_lidar = _kiss_slam_input(source)
    assert args[args.index("--dataloader") + 1] == ("kitti" if corrected else "generic")
    assert (T_cam_lidar is not None) == corrected
    if not corrected:
        assert Path(args[0]) == Path(source.sequence_dir) / "velodyne"


def _variant_result(name: str, quick: bool, slam_z_m: float, worst_kept_m: float) -> dict:
    run = {
        "frames": 10,
        "kiss_icp_xyz_m": [0.3, 0.3, 1.0],
        "kiss_icp_ate_m": 1.1,
        "slam_xyz_m": [0.1, 0.1, slam_z_m],
        "slam_ate_m": 0.2,
        "verified": 2,
        "kept": 2,
        "kept_loop_errors": [[worst_kept_m, 0.1], [0.01, 0.2]],
        "worst_kept_m": worst_kept_m,
        "worst_kept_deg": 0.2,
        "pitch_bias_mrad_per_100m": 1.0,
        "rejections": {},
        "timing_s": [5.0, 4.5, 6.0],
    }
    return {
        "machine": "test machine",
        "date": "2026-01-01T00:00:00",
        "quick": quick,
        "command": f"python -m benchmarks.bench_variants --variants '{name}'",
        "before_sets": [],
        "runs": {name: run},
        "before": {},
        "kiss_slam": {},
    }


def test_variant_results_combine_into_one_table_with_targets(tmp_path):
    files = []
    for name, z, worst in (("sparse", 0.2, 0.1), ("periodic", 0.7, 1.5)):
        path = tmp_path / f"{name}.json"
        result = _variant_result(name, False, z, worst)
        if name == "sparse":  # results written before the unaligned column lack it
            result["runs"][name]["slam_unaligned"] = [0.5, 0.05, 0.3]
        path.write_text(json.dumps(result))
        files.append(path)
    out = tmp_path / "all.md"
    assert bench_variants.main(["--combine", *map(str, files), "--out", str(out)]) == 0
    report = out.read_text()
    assert report.count("| sparse | 10 |") == 1 and report.count("| periodic | 10 |") == 1
    assert "| 0.50 / 0.05 / 0.30 |" in report and "/ 0.70 | - |" in report
    assert "- sparse: z ratio 0.20 (met); worst kept loop 0.10 m / 0.20 deg (met)" in report
    assert "- periodic: z ratio 0.70 (missed); worst kept loop 1.50 m / 0.20 deg (missed)" in report
    assert report.count("Combined from `") == 2
    combined = json.loads(out.with_suffix(".json").read_text())
    assert set(combined["runs"]) == {"sparse", "periodic"}

    quick = tmp_path / "quick.json"
    quick.write_text(json.dumps(_variant_result("noise", True, 0.1, 0.1)))
    assert bench_variants.main(["--combine", str(files[0]), str(quick), "--out", str(out)]) == 2
    assert bench_variants.main(["--combine", str(files[0]), str(files[0]), "--out", str(out)]) == 2


def test_throughput_report_states_ours_cpu_floor_against_kiss_slam():
    from benchmarks.throughput_report import _cpu_floor_lines

    runs = {
        "after": {"ours": {"cpu_s": 600.0, "wall_s": 350.0}, "kiss_slam": {"wall_s": 250.0}},
        "before abc": {"ours": {"cpu_s": 700.0, "wall_s": 400.0}},
    }
    lines = _cpu_floor_lines({"cores": 2, "runs": runs})
    after = next(line for line in lines if line.startswith("- after:"))
    assert "is 300 s, 1.20x KISS-SLAM's wall" in after and "1.17x that floor" in after
    assert "at most 500 CPU-s" in after
    before = next(line for line in lines if line.startswith("- before abc:"))
    assert "is 350 s, 1.40x" in before  # against the invocation's one KISS-SLAM run
    assert _cpu_floor_lines({"runs": runs}) == []  # no core count recorded: no claim


def test_throughput_report_names_a_before_run_the_harness_cannot_measure(tmp_path, monkeypatch):
    """A ``--before`` revision older than the harness is a skipped row with its reason, not a
    report that fails on the runs that were measured."""
    from benchmarks import throughput_report
    from benchmarks.harness.paths import RESULTS_DIR
    from benchmarks.harness.repeat import restore_all

    saved = restore_all(json.loads((RESULTS_DIR / "throughput.json").read_text()))
    saved["runs"]["before abc"] = {"code": "abc", "ours": {"skipped": "too old for the harness"}}
    monkeypatch.setattr(throughput_report, "REPORT", tmp_path / "throughput.md")
    throughput_report.write_report(saved)
    text = (tmp_path / "throughput.md").read_text()
    assert "- before abc, ours: skipped (too old for the harness)" in text
    assert "| after |" in text


def _slam_run(frames: int, loop_errors: list) -> dict:
    return {
        "frames": frames,
        "submaps": 4,
        "candidates": 3,
        "verified": len(loop_errors),
        "kept": sum(1 for *_, kept in loop_errors if kept),
        "loop_errors": loop_errors,
        "ate_odometry_m": 1.0,
        "ate_slam_m": 0.5,
        "ate_xyz_odometry_m": [0.5, 0.5, 0.5],
        "ate_xyz_slam_m": [0.2, 0.2, 0.2],
        "mesh_accuracy_m": 0.15,
        "remap_events": 2,
        "remap_moved": 5,
        "move_all_s": [2.0, 1.0, 4.0],
        "move_all_submaps": 4,
        "move_all_frames": frames,
        "submap_voxels_mean": 1000.0,
    }


def test_slam_section_shows_every_timing_with_its_range():
    from benchmarks import bench_slam

    lidar = _slam_run(550, [[0.1, 0.5, True], [2.5, 0.5, True], [3.0, 0.1, False]])
    room = {
        **_slam_run(240, []),
        "remap_vs_scratch_m": [0.001, 0.002],
        "remap_vs_scratch_median_m": [0.0005, 0.0006],
        "scratch_encode_s": [4.0, 5.0, 4.5],
        "scratch_encode_points": 1000,
        "accuracy_m": 0.006,
        "completion_m": 0.1,
        "completion_ratio": 0.45,
    }
    text = bench_slam.report(
        {"quick": True, "lidar_kiss": lidar, "room": room},
        "python -m benchmarks.bench_slam --quick",
    )
    assert f"median of {REPEATS} runs (min-max)" in text and "550 scans" in text
    assert "| 2 / 1 |" in text  # two loops beyond 1 m, one of them kept
    assert "| 2.00 (1.00-4.00) | 2.0 (1.0-4.0) | 275 (138-550) |" in text
    assert "| 4.5 (4.0-5.0) (1000 points) |" in text


def test_localise_kitchen_without_the_data_is_skipped_with_its_reason(tmp_path, monkeypatch):
    """The real 7-Scenes split runs in quick mode; without its frames it is a skipped section
    that says where they belong, not a failed benchmark."""
    from benchmarks import bench_localise

    assert "kitchen" in bench_localise.SCENARIOS
    absent = tmp_path / "7scenes_redkitchen"
    monkeypatch.setattr(bench_localise, "KITCHEN_ROOT", absent)
    with pytest.raises(FileNotFoundError) as missing:
        bench_localise.split("kitchen", full=False)
    assert str(absent) in str(missing.value)
    text = bench_localise.report({"kitchen": {"skipped": str(missing.value)}}, "command")
    assert f"### kitchen\n\nSkipped: {missing.value}." in text
