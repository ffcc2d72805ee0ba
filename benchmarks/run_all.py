"""Run every ``benchmarks/bench_*.py`` and assemble ``BENCHMARKS.md`` from their sections.

    python -m benchmarks.run_all [--quick] [--only NAME ...] [--assemble]

Each benchmark runs in its own process (``python -m benchmarks.bench_<name> [--quick]``) and
writes ``benchmarks/results/<name>.md``. A benchmark that fails, times out or writes no section
is reported in ``BENCHMARKS.md`` (with the tail of its log) and does not stop the others. Logs go
to ``benchmarks/out/logs/<name>.log``; the status of the last run to
``benchmarks/results/_run_all.json``, which ``--assemble`` reuses to rebuild ``BENCHMARKS.md``
from the existing sections without running anything.

``--quick`` passes ``--quick`` to every benchmark and holds the whole run to a wall-clock budget
(14 minutes by default): each benchmark gets the time that is left, and the ones that no longer
fit are reported as skipped.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import platform
import shlex
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from common.atomic_io import write_text_atomic

log = logging.getLogger("benchmarks.run_all")

REPO_ROOT = Path(__file__).resolve().parents[1]
BENCH_DIR = REPO_ROOT / "benchmarks"
RESULTS_DIR = BENCH_DIR / "results"
LOG_DIR = BENCH_DIR / "out" / "logs"
STATUS_FILE = RESULTS_DIR / "_run_all.json"
OUTPUT_FILE = REPO_ROOT / "BENCHMARKS.md"

# Components first, then whole-pipeline runs, then what measures the pipeline's logging.
PREFERRED_ORDER = (
    "metrics",
    "sources",
    "generate",
    "odometry",
    "encoder",
    "networks",
    "prior",
    "mapping",
    "neural_map",
    "transform",
    "meshing",
    "loop_closure",
    "loops",
    "pose_graph",
    "pipeline",
    "slam",
    "demo",
    "rerun",
)
QUICK_BUDGET_S = 14 * 60
FULL_TIMEOUT_S = 3 * 3600
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
    """Names ``<name>`` of every ``bench_<name>.py``, in the order they should run."""
    names = [path.stem.removeprefix("bench_") for path in bench_dir.glob("bench_*.py")]
    rank = {name: index for index, name in enumerate(PREFERRED_ORDER)}
    middle = rank.get("pipeline", len(rank))
    return sorted(names, key=lambda name: (rank.get(name, middle - 0.5), name))


def machine_description() -> dict[str, str]:
    """Machine facts for the report header."""
    from importlib import metadata

    def version(package: str) -> str:
        try:
            return metadata.version(package)
        except metadata.PackageNotFoundError:
            return "not installed"

    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": str(os.cpu_count()),
        "python": platform.python_version(),
        "torch": version("torch"),
        "torch_threads": _torch_threads(),
        "rerun_sdk": version("rerun-sdk"),
    }


def _torch_threads() -> str:
    try:
        import torch
    except ImportError:
        return "n/a"
    return str(torch.get_num_threads())


def git_revision() -> str:
    """``git describe --always --dirty`` of the repository, or ``unknown``."""
    try:
        result = subprocess.run(
            ["git", "describe", "--always", "--dirty"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=20,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return result.stdout.strip() or "unknown"


def _tail(path: Path, chars: int = LOG_TAIL_CHARS) -> str:
    if not path.is_file():
        return ""
    text = path.read_text(errors="replace")
    return text[-chars:]


def run_one(name: str, *, quick: bool, timeout_s: float) -> BenchStatus:
    """Run ``benchmarks.bench_<name>`` in a subprocess; its output goes to the log file."""
    command = [sys.executable, "-m", f"benchmarks.bench_{name}", *(["--quick"] if quick else [])]
    shown = "python " + " ".join(shlex.quote(part) for part in command[1:])
    result_file = RESULTS_DIR / f"{name}.md"
    LOG_DIR.mkdir(parents=True, exist_ok=True)
    log_file = LOG_DIR / f"{name}.log"
    started = time.time()
    returncode: int | None = None
    status = "ok"
    with log_file.open("w") as stream:
        try:
            completed = subprocess.run(
                command,
                cwd=REPO_ROOT,
                stdout=stream,
                stderr=subprocess.STDOUT,
                timeout=timeout_s,
                check=False,
            )
            returncode = completed.returncode
        except subprocess.TimeoutExpired:
            status = "timeout"
    seconds = time.time() - started
    fresh = result_file.is_file() and result_file.stat().st_mtime >= started - 1.0
    detail = ""
    if status == "timeout":
        detail = f"killed after {timeout_s:.0f} s"
    elif returncode != 0:
        status = "failed"
        detail = f"exit status {returncode}"
    elif not fresh:
        status = "no-output"
        detail = f"exited 0 but did not write {result_file.relative_to(REPO_ROOT)}"
    if status != "ok":
        detail += "\n\n" + _tail(log_file)
    return BenchStatus(name, status, round(seconds, 1), returncode, shown, detail)


def assemble(status_record: dict | None = None, *, output: Path = OUTPUT_FILE) -> Path:
    """Rebuild ``BENCHMARKS.md`` from ``benchmarks/results/*.md`` and the last run's status."""
    if status_record is None and STATUS_FILE.is_file():
        status_record = json.loads(STATUS_FILE.read_text())
    status_record = status_record or {}
    statuses = {s["name"]: s for s in status_record.get("benchmarks", [])}
    sections = {path.stem: path for path in RESULTS_DIR.glob("*.md")}
    names = [n for n in discover() if n in sections or n in statuses]
    names += sorted(n for n in set(sections) | set(statuses) if n not in names)
    machine = status_record.get("machine") or machine_description()
    now = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")

    lines = [
        "# Benchmarks",
        "",
        "Measured numbers only; every section below was written by its own script under",
        "`benchmarks/` and states its exact command. Re-create this file with",
        "`python -m benchmarks.run_all [--quick]`, or rebuild it from the existing sections with",
        "`python -m benchmarks.run_all --assemble`.",
        "",
        f"- Run command: `{status_record.get('command', 'unknown (sections assembled only)')}`",
        f"- Run started: {status_record.get('started', 'unknown')}; assembled: {now}",
        f"- Mode: {status_record.get('mode', 'unknown')}; revision: "
        f"{status_record.get('revision', git_revision())}",
        "- Machine: "
        + "; ".join(f"{key} {value}" for key, value in machine.items() if key != "platform"),
        f"- Platform: {machine.get('platform', '')}",
        "",
        "| benchmark | status | wall time [s] | command |",
        "|---|---|---:|---|",
    ]
    for name in names:
        state = statuses.get(name)
        if state is None:
            lines.append(f"| {name} | section only (not run by run_all) | | |")
        else:
            lines.append(
                f"| [{name}](#{name}) | {state['status']} | {state['seconds']:.1f} | "
                f"`{state['command']}` |"
            )
    lines.append("")
    for name in names:
        lines.append(f'<a id="{name}"></a>')
        lines.append("")
        state = statuses.get(name)
        if state is not None and state["status"] != "ok":
            lines += [
                f"## {name}: {state['status'].upper()}",
                "",
                f"Command: `{state['command']}`",
                "",
                "```text",
                state["detail"].strip(),
                "```",
                "",
            ]
            if name in sections:
                lines += ["Section left over from an earlier run (may be stale):", ""]
        if name in sections:
            lines += [sections[name].read_text().rstrip(), ""]
    write_text_atomic(output, "\n".join(lines).rstrip() + "\n")
    return output


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="pass --quick to each benchmark")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="run only these benchmarks")
    parser.add_argument(
        "--assemble", action="store_true", help="only rebuild BENCHMARKS.md from results/*.md"
    )
    parser.add_argument(
        "--budget-s",
        type=float,
        default=None,
        help=f"total wall-clock budget (default {QUICK_BUDGET_S} s with --quick, else none)",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    if args.assemble:
        log.info("wrote %s", assemble())
        return 0

    names = discover()
    if args.only:
        unknown = sorted(set(args.only) - set(names))
        if unknown:
            parser.error(f"no benchmarks/bench_<name>.py for: {', '.join(unknown)}")
        names = [name for name in names if name in args.only]
    budget_s = args.budget_s or (QUICK_BUDGET_S if args.quick else None)
    started = time.time()
    record = {
        "command": " ".join(["python -m benchmarks.run_all", *(argv or sys.argv[1:])]),
        "started": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "mode": "quick" if args.quick else "full",
        "revision": git_revision(),
        "machine": machine_description(),
        "benchmarks": [],
    }
    if args.only and STATUS_FILE.is_file():
        # Keep the earlier outcome of the benchmarks this partial run leaves alone.
        previous = json.loads(STATUS_FILE.read_text()).get("benchmarks", [])
        record["benchmarks"] = [s for s in previous if s["name"] not in names]
    for name in names:
        remaining = FULL_TIMEOUT_S if budget_s is None else budget_s - (time.time() - started)
        if remaining < 5:
            state = BenchStatus(name, "skipped", 0.0, None, f"bench_{name}", "budget exhausted")
        else:
            log.info("running bench_%s (%.0f s left)", name, remaining)
            state = run_one(name, quick=args.quick, timeout_s=remaining)
        log.info("  %s: %s in %.1f s", name, state.status, state.seconds)
        record["benchmarks"].append(asdict(state))
        write_text_atomic(STATUS_FILE, json.dumps(record, indent=2) + "\n")
    record["total_seconds"] = round(time.time() - started, 1)
    write_text_atomic(STATUS_FILE, json.dumps(record, indent=2) + "\n")
    log.info("wrote %s (%.0f s total)", assemble(record), record["total_seconds"])
    return 0 if all(s["status"] == "ok" for s in record["benchmarks"]) else 1


if __name__ == "__main__":
    sys.exit(main())
