"""What a reliability case is and how it is run (``benchmarks/bench_reliability.py``): a command
run as a user would, its exit code, the line that tells the user what happened, what a probe
saw, and the command's own peak RSS (:class:`~benchmarks.harness.child.MeasuredCommand`)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from benchmarks.harness.child import MeasuredCommand

PY = sys.executable


@dataclass
class Outcome:
    status: int | None
    message: str
    probe: str = ""
    peak_rss_mb: float | None = None


@dataclass
class Case:
    number: str
    title: str
    command: str
    run: Callable[[Path, Path, Path], Outcome]  # (code root, work folder, base run) -> outcome
    quick: bool = True
    group: str = "general"


_RUST_LOG = re.compile(r"^\d{4}-\d\d-\d\dT\S+ +(ERROR|WARN|INFO)")
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def message_of(stderr: str, stdout: str = "") -> str:
    """The line that tells the user what happened (Rerun's own log lines left out)."""
    lines = [_ANSI.sub("", line).strip() for line in stderr.splitlines()]
    lines = [line for line in lines if line and not _RUST_LOG.match(line)]
    for prefix in ("error:", "WARNING", "warning"):
        for line in lines:
            if line.startswith(prefix):
                return line
    if any(line.startswith("Traceback") for line in lines):
        return f"traceback ({len(lines)} lines): {lines[-1]}"
    if lines:
        return lines[0]
    out = [line for line in stdout.splitlines() if line.strip()]
    return f"(stdout) {out[0]}" if out else "(no output)"


def run(
    code: Path, args: list[str], timeout: float = 600, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    """``args`` with ``code`` on ``PYTHONPATH`` (and ``env`` on top of this environment); the
    result's ``peak_rss_mb`` is the command's own peak resident memory (its waited-for children
    included)."""
    env = {**os.environ, **(env or {}), "PYTHONPATH": str(code)}
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        command = MeasuredCommand(args, cwd=code, env=env, stdout=out, stderr=err)
        timer = threading.Timer(timeout, command.kill)
        timer.start()
        try:
            finished = command.wait()
        finally:
            timer.cancel()
        out.seek(0)
        err.seek(0)
        texts = (stream.read().decode(errors="replace") for stream in (out, err))
        result = subprocess.CompletedProcess(args, finished.returncode, *texts)
    result.peak_rss_mb = finished.peak_rss_mb  # type: ignore[attr-defined]
    return result


def outcome(result: subprocess.CompletedProcess, probe: str = "") -> Outcome:
    peak = getattr(result, "peak_rss_mb", None)
    return Outcome(result.returncode, message_of(result.stderr, result.stdout), probe, peak)
