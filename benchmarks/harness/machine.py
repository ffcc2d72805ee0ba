"""The machine and code a measurement was taken on: one description for every section."""

from __future__ import annotations

import datetime as dt
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

from benchmarks.harness.paths import REPO


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (the architecture where that is unreadable)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def version(package: str) -> str:
    """Installed version of ``package``, or ``not installed``."""
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "not installed"


def git_revision(checkout: Path = REPO) -> str:
    """``git describe --always --dirty`` of ``checkout`` (``-dirty``: uncommitted changes)."""
    try:
        result = subprocess.run(
            ["git", "describe", "--always", "--dirty"],
            cwd=checkout,
            capture_output=True,
            text=True,
            timeout=20,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return result.stdout.strip() or "unknown"


def load_average() -> str:
    """The 1, 5 and 15-minute load averages."""
    return ", ".join(f"{value:.1f}" for value in os.getloadavg())


def now() -> str:
    """The current time in UTC, to the minute."""
    return dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def machine_description() -> dict[str, str]:
    """CPU, cores, load, versions, revision and date, as labelled strings."""
    return {
        "cpu": cpu_model(),
        "cores": str(os.cpu_count()),
        "load average (1, 5, 15 min)": load_average(),
        "python": platform.python_version(),
        "torch": version("torch"),
        "kiss-icp": version("kiss-icp"),
        "opencv": version("opencv-python-headless"),
        "rerun-sdk": version("rerun-sdk"),
        "platform": platform.platform(),
        "revision": git_revision(),
        "date": now(),
    }


SECTION_KEYS = ("cpu", "cores", "load average (1, 5, 15 min)", "torch", "revision", "date")
"""What a section's machine line repeats of :func:`machine_description`; the report's header
(``benchmarks.run_all``) holds the rest (the other versions, the platform) once."""


def machine_line() -> str:
    """:func:`machine_description` as one line for a section header (:data:`SECTION_KEYS`)."""
    described = machine_description()
    return "; ".join(f"{key} {described[key]}" for key in SECTION_KEYS)


def section_header(title: str, command: str) -> list[str]:
    """The first lines of a benchmark's section: its title, exact command and machine."""
    return [f"## {title}", "", f"- Command: `{command}`", f"- Machine: {machine_line()}"]


def proc_memory_kib(pid: int | str = "self") -> dict[str, int]:
    """``VmRSS`` and ``VmHWM`` (current and peak resident memory, KiB) of process ``pid`` from
    /proc; empty where it cannot be read (e.g. the process has ended)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return {}
    fields = (line.partition(":") for line in lines)
    return {key: int(value.split()[0]) for key, _, value in fields if key in ("VmRSS", "VmHWM")}
