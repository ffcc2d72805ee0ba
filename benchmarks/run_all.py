"""Run every benchmark and regenerate ``BENCHMARKS.md`` from this invocation's sections.

    python -m benchmarks.run_all [--quick] [--only NAME ...] [--before REV] [--assemble]

Each ``benchmarks/bench_<name>.py`` of :data:`BENCHMARKS` runs in its own process and writes
``benchmarks/results/<name>.md``; ``benchmarks/results/`` is emptied first, so the report holds
this invocation's sections only. A benchmark that fails, times out or writes no section is
reported with the tail of its log (``benchmarks/out/logs/``) and does not stop the others.
``--before REV`` goes to the benchmarks of :data:`BEFORE_AFTER` (each measures REV checked out
beside this tree in the same invocation). ``--assemble`` only rebuilds ``BENCHMARKS.md`` from
``results/run_all.json``. The report links the archived runs ("History"), must stay under
:data:`MAX_REPORT_BYTES`, and has its sections' relative links rebased onto its own folder.
``--quick`` passes ``--quick`` on and holds the run to a budget (35 minutes by default), each
benchmark getting at most twice its fair share of what is left.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from benchmarks.harness.history import history_lines
from benchmarks.harness.machine import load_average, machine_description, now
from benchmarks.harness.paths import REPO, RESULTS_DIR, WORK_DIR
from benchmarks.harness.results import table
from common.atomic_io import write_text_atomic

log = logging.getLogger("benchmarks.run_all")

BENCH_DIR = REPO / "benchmarks"
LOG_DIR = WORK_DIR / "logs"
STATUS_NAME = "run_all.json"
OUTPUT_FILE = REPO / "BENCHMARKS.md"
MAX_REPORT_BYTES = 60_000
"""The assembled report's size limit: over it, :func:`assemble` says so at the top of the
report and :func:`main` fails."""
RELATIVE_LINK = re.compile(r"\]\((?![a-z][a-z0-9+.-]*:|#|/)([^)\s]+)\)")
"""A Markdown link or image target that is a relative path (no scheme, anchor or root)."""

BENCHMARKS = (
    "odometry",
    "prior",
    "mapping",
    "keyframing",
    "accuracy",
    "slam",
    "throughput",
    "map_size",
    "variants",
    "lidar_map",
    "real",
    "merge",
    "localise",
    "fleet",
    "rerun",
    "reliability",
)
"""Every ``bench_<name>.py``, in the order they run: components, then whole-pipeline runs, then
what measures the pipeline's logging (tests/test_benchmarks.py keeps it in sync with the files)."""
BEFORE_AFTER = ("accuracy", "keyframing", "throughput", "map_size", "reliability")
"""Benchmarks that accept ``--before REV``."""
QUICK_BUDGET_S = 35 * 60
FULL_TIMEOUT_S = 4 * 3600
LOG_TAIL_CHARS = 3000


@dataclass
class BenchStatus:
    """Outcome of one benchmark process."""

    name: str
    status: str  # ok | failed | timeout | no-output | skipped
    seconds: float
    returncode: int | None
    command: str
    detail: str = ""


def discover(bench_dir: Path = BENCH_DIR) -> list[str]:
    """Names ``<name>`` of the ``bench_<name>.py`` files present, sorted."""
    return sorted(path.stem.removeprefix("bench_") for path in bench_dir.glob("bench_*.py"))


def _tail(path: Path, chars: int = LOG_TAIL_CHARS) -> str:
    return path.read_text(errors="replace")[-chars:] if path.is_file() else ""


def bench_command(
    name: str, *, quick: bool, before: str | None, before_in: tuple[str, ...] = BEFORE_AFTER
) -> list[str]:
    """The command line that runs ``bench_<name>`` (without the interpreter); ``before`` goes to
    the benchmarks of ``before_in``."""
    command = ["-m", f"benchmarks.bench_{name}", *(["--quick"] if quick else [])]
    if before and name in before_in:
        command += ["--before", before]
    return command


def run_one(
    name: str,
    *,
    quick: bool,
    before: str | None,
    timeout_s: float,
    before_in: tuple[str, ...] = BEFORE_AFTER,
) -> BenchStatus:
    """Run ``benchmarks.bench_<name>`` in a subprocess; its output goes to its log file."""
    args = bench_command(name, quick=quick, before=before, before_in=before_in)
    shown = shlex.join(["python", *args])
    result_file = RESULTS_DIR / f"{name}.md"
    LOG_DIR.mkdir(parents=True, exist_ok=True)
    log_file = LOG_DIR / f"{name}.log"
    started = time.time()
    returncode: int | None = None
    status, detail = "ok", ""
    with log_file.open("w") as stream:
        # its own process group, so that a timeout also ends the processes it spawned
        child = subprocess.Popen(
            [sys.executable, *args],
            cwd=REPO,
            stdout=stream,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            returncode = child.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()
            status, detail = "timeout", f"killed after {timeout_s:.0f} s"
    if status == "ok" and returncode != 0:
        status, detail = "failed", f"exit status {returncode}"
    elif status == "ok" and not result_file.is_file():
        status = "no-output"
        detail = f"exited 0 but did not write {result_file.relative_to(REPO)}"
    if status != "ok":
        detail += "\n\n" + _tail(log_file)
    return BenchStatus(name, status, round(time.time() - started, 1), returncode, shown, detail)


def header_lines(record: dict) -> list[str]:
    """The report's header: what this invocation was, where and when it ran."""
    machine = dict(record["machine"])
    revision = machine.pop("revision", "unknown")
    machine.pop("date", None)
    invoked = record.get("invoked_as")
    command = f"`{record['command']}`" + (f" (via `{invoked}`)" if invoked else "")
    total = record.get("total_seconds")
    return [
        "# Benchmarks",
        "",
        "Measured numbers only, all from the one invocation described here; every section was",
        "written by its own script under `benchmarks/` and states its exact command.",
        "",
        f"- Command: {command}",
        f"- Revision: {revision}"
        + (" (uncommitted changes)" if revision.endswith("-dirty") else ""),
        f"- Started: {record['started']}; finished: {record.get('finished', 'not finished')}"
        + (f"; wall time {total:.0f} s" if total is not None else ""),
        f"- Mode: {record['mode']}"
        + (f"; before/after against `{record['before']}`" if record.get("before") else ""),
        "- Machine: " + "; ".join(f"{key} {value}" for key, value in machine.items()),
        f"- Load average at the end: {record.get('load_end', 'n/a')} (the machine is shared with "
        "other jobs: wall times are upper bounds, frames/s lower bounds)",
        "- Sections: only the benchmarks this invocation ran; `benchmarks/results/` was emptied "
        "at its start, so nothing from an earlier invocation is mixed in.",
        "",
    ]


def assemble(record: dict, *, results_dir: Path = RESULTS_DIR, output: Path = OUTPUT_FILE) -> Path:
    """Write ``output`` from an invocation ``record`` and the sections in ``results_dir``, then
    the "History" section that links the archived runs; a report over
    :data:`MAX_REPORT_BYTES` starts with a warning (:func:`main` then fails)."""
    statuses = record.get("benchmarks", [])
    lines = header_lines(record)
    lines += table(
        "benchmark | status | wall time [s] | command",
        (
            [
                f"[{s['name']}](#{s['name']})",
                s["status"],
                f"{s['seconds']:.1f}",
                f"`{s['command']}`",
            ]
            for s in statuses
        ),
        "llrl",
    )
    lines.append("")
    for state in statuses:
        name = state["name"]
        section = results_dir / f"{name}.md"
        lines += [f'<a id="{name}"></a>', ""]
        if state["status"] != "ok":
            lines += [f"## {name}: {state['status'].upper()}", "", f"Command: `{state['command']}`"]
            lines += ["", "```text", state["detail"].strip(), "```", ""]
        elif section.is_file():
            lines += [rebased_links(section.read_text(), results_dir, output).rstrip(), ""]
    lines += history_lines()
    text = "\n".join(lines).rstrip() + "\n"
    too_large = check_size(text)
    if too_large:
        text = text.replace("\n", f"\n\n**Warning: {too_large}.**\n", 1)
    write_text_atomic(output, text)
    return output


def rebased_links(text: str, results_dir: Path, output: Path) -> str:
    """``text`` of a section in ``results_dir`` with its relative links made relative to the
    folder of ``output``."""
    prefix = Path(os.path.relpath(results_dir, output.parent)).as_posix()
    return RELATIVE_LINK.sub(lambda link: f"]({prefix}/{link[1]})", text)


def check_size(text: str, limit: int = MAX_REPORT_BYTES) -> str | None:
    """Why ``text`` is too large for the report, or None when it fits ``limit`` bytes."""
    size = len(text.encode())
    if size <= limit:
        return None
    return (
        f"BENCHMARKS.md is {size / 1000:.0f} kB, over its {limit / 1000:.0f} kB limit: a "
        "section prints too much (keep long runs in benchmarks/archive/ and link them)"
    )


def clear_results(results_dir: Path = RESULTS_DIR) -> None:
    """Remove every file of an earlier invocation from ``results_dir``."""
    results_dir.mkdir(parents=True, exist_ok=True)
    for path in results_dir.iterdir():
        if path.is_file():
            path.unlink()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="pass --quick to each benchmark")
    parser.add_argument("--only", nargs="+", metavar="NAME", choices=BENCHMARKS)
    parser.add_argument("--before", metavar="REV", help="before/after tables against REV")
    parser.add_argument(
        "--before-in",
        nargs="+",
        metavar="NAME",
        choices=BEFORE_AFTER,
        default=list(BEFORE_AFTER),
        help="the benchmarks that measure --before (default: all that can). Those that import "
        "REV's modules (accuracy, keyframing, throughput, map_size) need REV to have today's "
        "module API; reliability runs REV's command line and works for any REV",
    )
    parser.add_argument("--assemble", action="store_true", help="only rebuild BENCHMARKS.md")
    parser.add_argument(
        "--budget-s",
        type=float,
        default=None,
        help=f"total wall-clock budget (default {QUICK_BUDGET_S} s with --quick, "
        "twice that with --before, else none)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    status_file = RESULTS_DIR / STATUS_NAME
    if args.assemble:
        if not status_file.is_file():
            log.error("%s: absent; run `python -m benchmarks.run_all` first", status_file)
            return 2
        log.info("wrote %s", assemble(json.loads(status_file.read_text())))
        return 0
    missing = sorted(set(discover()) ^ set(BENCHMARKS))
    if missing:
        log.error("run_all.BENCHMARKS and benchmarks/bench_*.py differ in: %s", ", ".join(missing))
        return 2
    names = [name for name in BENCHMARKS if not args.only or name in args.only]
    # --before measures two revisions in several benchmarks: twice the time
    quick_budget_s = QUICK_BUDGET_S * (2 if args.before and len(args.before_in) > 1 else 1)
    budget_s = args.budget_s or (quick_budget_s if args.quick else None)
    started = time.time()
    shown = sys.argv[1:] if argv is None else argv
    record = {
        "command": shlex.join(["python", "-m", "benchmarks.run_all", *shown]),
        "invoked_as": os.environ.get("BENCH_INVOKED_AS"),
        "started": now(),
        "mode": "quick" if args.quick else "full",
        "before": args.before,
        "machine": machine_description(),
        "benchmarks": [],
    }
    clear_results()
    for index, name in enumerate(names):
        remaining = FULL_TIMEOUT_S if budget_s is None else budget_s - (time.time() - started)
        if budget_s is not None:
            # at most twice a fair share of what is left, so one slow benchmark cannot starve
            # all that come after it
            remaining = min(remaining, 2 * remaining / (len(names) - index))
        if remaining < 5:
            command = shlex.join(["python", *bench_command(name, quick=args.quick, before=None)])
            state = BenchStatus(name, "skipped", 0.0, None, command, "budget exhausted")
        else:
            log.info("running bench_%s (%.0f s left)", name, remaining)
            state = run_one(
                name,
                quick=args.quick,
                before=args.before,
                timeout_s=remaining,
                before_in=tuple(args.before_in),
            )
        log.info("  %s: %s in %.1f s", name, state.status, state.seconds)
        record["benchmarks"].append(asdict(state))
        write_text_atomic(status_file, json.dumps(record, indent=2) + "\n")
    record.update(
        finished=now(), total_seconds=round(time.time() - started, 1), load_end=load_average()
    )
    write_text_atomic(status_file, json.dumps(record, indent=2) + "\n")
    report = assemble(record)
    log.info("wrote %s (%.0f s total)", report, record["total_seconds"])
    too_large = check_size(report.read_text())
    if too_large:
        log.error("%s", too_large)
        return 1
    return 0 if all(s["status"] == "ok" for s in record["benchmarks"]) else 1


if __name__ == "__main__":
    sys.exit(main())
