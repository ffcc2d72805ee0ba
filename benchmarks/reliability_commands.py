"""Reliability cases of the commands' arguments and environment (``bench_reliability.py --only
commands``): ``slam.eval`` bounds and bad files, config values that size memory or work, ``--rrd``
targets, ``--serve`` ports, ``RERUN=off``. Each cell says what the user saw and the command's peak
RSS; a case that exhausted memory or time would show it there. They run in the full benchmark
(not ``--quick``), which keeps the quick report within its size limit."""

from __future__ import annotations

import os
import socket
from pathlib import Path

from benchmarks.harness.net import free_port
from benchmarks.harness.reliability import PY, Case, Outcome, outcome, run

DEMO = ["demo", "--no-progress", "--frames", "0:6", "--set", "output.mesh_samples=1000"]


def _slam_run(code: Path, work: Path, *args: str, env: dict[str, str] | None = None):
    command = [PY, "-m", "slam.run", *DEMO, *args, "--out", str(work / "run")]
    return run(code, command, timeout=300, env=env)


def _left(work: Path) -> str:
    return f"run folder: {'written' if (work / 'run').exists() else 'none'}"


def _eval_case(*args: str):
    def case(code: Path, work: Path, base: Path) -> Outcome:
        return outcome(run(code, [PY, "-m", "slam.eval", str(base), "--no-plots", *args], 300))

    return case


def _set_case(*assignments: str):
    def case(code: Path, work: Path, base: Path) -> Outcome:
        sets = [arg for item in assignments for arg in ("--set", item)]
        return outcome(_slam_run(code, work, "--no-viz", *sets), _left(work))

    return case


def case_garbage_gt_mesh(code: Path, work: Path, base: Path) -> Outcome:
    garbage = work / "garbage.ply"
    garbage.write_bytes(os.urandom(4096))
    return _eval_case("--gt-mesh", str(garbage))(code, work, base)


def case_rrd_exists(code: Path, work: Path, base: Path) -> Outcome:
    target = work / "keep.rrd"
    target.write_bytes(b"someone else's recording")
    result = _slam_run(code, work, "--rrd", str(target))
    intact = target.read_bytes() == b"someone else's recording"
    return outcome(result, f"existing file {'intact' if intact else 'OVERWRITTEN'}; {_left(work)}")


def case_rrd_unwritable(code: Path, work: Path, base: Path) -> Outcome:
    return outcome(_slam_run(code, work, "--rrd", "/proc/x/recording.rrd"), _left(work))


def case_rerun_off(code: Path, work: Path, base: Path) -> Outcome:
    result = _slam_run(code, work, env={"RERUN": "off"})
    return outcome(result, f"recording: {(work / 'run' / 'recording.rrd').exists()}")


def case_grpc_port_taken(code: Path, work: Path, base: Path) -> Outcome:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        grpc = taken.getsockname()[1]
        result = _slam_run(
            code, work, "--serve", "--set", "viz.serve_linger_s=0",
            "--set", f"viz.serve_grpc_port={grpc}", "--set", f"viz.serve_web_port={free_port()}",
        )  # fmt: skip
    return outcome(result, _left(work))


def case_foreign_bind_ip(code: Path, work: Path, base: Path) -> Outcome:
    result = _slam_run(code, work, "--serve", "--set", "viz.serve_bind_ip=8.8.8.8")
    return outcome(result, _left(work))


def case_absurd_generated_config(code: Path, work: Path, base: Path) -> Outcome:
    folder = work / "absurd"
    folder.mkdir()
    for item in base.iterdir():
        if item.is_file():
            (folder / item.name).write_bytes(item.read_bytes())
    config = (folder / "config.yaml").read_text()
    if "num_frames: 240" not in config:
        return Outcome(None, "case failed: the base run's config has no num_frames: 240")
    (folder / "config.yaml").write_text(config.replace("num_frames: 240", "num_frames: 1000000000"))
    return outcome(run(code, [PY, "-m", "slam.eval", str(folder), "--no-plots"], timeout=300))


def _eval_arg(number: str, flag: str, value: str) -> Case:
    return _command(
        number,
        f"slam.eval {flag} {value}",
        f"slam.eval RUN {flag} {value}",
        _eval_case(flag, value),
    )


def _set(number: str, assignment: str) -> Case:
    return _command(number, assignment, f"slam.run demo --set {assignment}", _set_case(assignment))


def _command(number: str, title: str, command: str, fn) -> Case:
    return Case(number, title, command, fn, quick=False, group="commands")


COMMAND_CASES = [
    _eval_arg("C1", "--cull-distance-m", "0"),
    _eval_arg("C1", "--cull-distance-m", "0.0001"),
    _eval_arg("C2", "--samples", "-5"),
    _eval_arg("C2", "--samples", "1e10"),
    _command(
        "C2",
        "slam.eval --gt-mesh of random bytes",
        "slam.eval RUN --gt-mesh garbage.ply",
        case_garbage_gt_mesh,
    ),
    _command(
        "C2",
        "run config with generated.num_frames 10^9",
        "slam.eval RUN (edited config.yaml)",
        case_absurd_generated_config,
    ),
    _set("C3", "mapping.voxel_size_m=inf"),
    _set("C3", "mapping.voxel_size_m=1e-9"),
    _set("C3", "mapping.encoder_table_nodes=1000000"),
    _set("C3", "threads=1000000"),
    _command(
        "C5",
        "--serve with the data port taken",
        "slam.run demo --serve (gRPC port in use)",
        case_grpc_port_taken,
    ),
    _command(
        "C5",
        "--serve bound to 8.8.8.8",
        "slam.run demo --serve --set viz.serve_bind_ip=8.8.8.8",
        case_foreign_bind_ip,
    ),
    _command("C6", "--rrd onto an existing file", "slam.run demo --rrd EXISTING", case_rrd_exists),
    _command(
        "C6", "--rrd under /proc", "slam.run demo --rrd /proc/x/recording.rrd", case_rrd_unwritable
    ),
    _command("C9", "RERUN=off", "RERUN=off slam.run demo", case_rerun_off),
]
