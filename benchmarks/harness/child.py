"""Measured child processes: a Python function in a fresh interpreter, or a command.

Each measurement runs in its own process so that its peak resident memory is its own. Both
report wall time, CPU time (user + system, all threads) and peak RSS of the child alone.
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
import resource
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks.harness.paths import REPO

CODE_UNDER_TEST = ("slam", "frontends", "mapping", "common")
"""Top-level packages that ``code=`` swaps for a checkout's."""


class UnsupportedRevision(RuntimeError):
    """A checkout whose modules do not have today's layout (names, paths) cannot be measured by
    today's benchmark code; its before/after row says so in one line."""


@dataclass
class Usage:
    """What a child process cost."""

    wall_s: float
    cpu_s: float
    peak_rss_mb: float


def _use_code(checkout: str | None) -> None:
    """Pool initializer: import the code under test from ``checkout`` (``benchmarks`` stays this
    tree's); packages under test that spawning already imported are forgotten first."""
    if checkout is not None:
        for name in list(sys.modules):
            if name.split(".")[0] in CODE_UNDER_TEST:
                del sys.modules[name]
        sys.path.insert(0, checkout)
        os.environ["PYTHONPATH"] = os.pathsep.join(
            [checkout, *filter(None, [os.environ.get("PYTHONPATH")])]
        )


def _measured(fn, args: tuple) -> tuple[Any, Usage]:
    start, cpu_start = time.perf_counter(), time.process_time()
    result = fn(*args)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return result, Usage(wall, cpu, peak_mb)


def in_child_measured(fn, *args, code: Path | None = None) -> tuple[Any, Usage]:
    """``fn(*args)`` in a spawned interpreter (``code``: the checkout whose packages it
    imports); its result and what the call cost there. A checkout that lacks a module or name
    the benchmark imports raises :class:`UnsupportedRevision`."""
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(
        max_workers=1,
        mp_context=context,
        initializer=_use_code,
        initargs=(None if code is None else str(code),),
    ) as pool:
        try:
            return pool.submit(_measured, fn, args).result()
        except ImportError as error:
            if code is None:
                raise
            raise UnsupportedRevision(f"unsupported: another module layout ({error})") from error


def in_child(fn, *args, code: Path | None = None) -> Any:
    """``fn(*args)`` in a spawned interpreter; only its result."""
    return in_child_measured(fn, *args, code=code)[0]


@dataclass
class CommandResult:
    """A finished command: exit status, its output (or log file) and its :class:`Usage`."""

    returncode: int
    stdout: str
    usage: Usage


def run_command(
    command: list[str],
    *,
    cwd: Path,
    env: dict[str, str] | None = None,
    timeout_s: float = 4 * 3600,
    log_file: Path | None = None,
    on_poll=None,
) -> CommandResult:
    """Run ``command``, measured with ``wait4``; its output goes to ``log_file`` (else it is
    captured), ``on_poll(pid)`` is called about once a second, and past ``timeout_s`` it is
    killed (status -9)."""
    start = time.perf_counter()
    stream = open(log_file, "w") if log_file is not None else subprocess.PIPE
    try:
        child = subprocess.Popen(
            command, cwd=cwd, env=env, stdout=stream, stderr=subprocess.STDOUT, text=True
        )
        if log_file is None:
            # a reader thread keeps the pipe drained; wait4 below still gets the rusage
            output: list[str] = []
            import threading

            reader = threading.Thread(target=lambda: output.append(child.stdout.read()))
            reader.start()
        while True:
            pid, status, usage = os.wait4(child.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() - start > timeout_s:
                child.kill()
            if on_poll is not None:
                on_poll(child.pid)
            time.sleep(0.5)
        child.returncode = os.waitstatus_to_exitcode(status)
        text = ""
        if log_file is None:
            reader.join()
            text = "".join(output)
    finally:
        if log_file is not None:
            stream.close()
    cost = Usage(
        time.perf_counter() - start, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024
    )
    return CommandResult(child.returncode, text, cost)


def run_module(module: str, args: list[str], log_file: Path) -> tuple[float, float]:
    """``python -m module args`` in this tree, its output in ``log_file``: (wall s, peak RSS
    MB); a failure raises, naming the log."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    done = run_command([sys.executable, "-m", module, *args], cwd=REPO, env=env, log_file=log_file)
    if done.returncode != 0:
        raise RuntimeError(f"{module} {' '.join(args)} failed; see {log_file}")
    return done.usage.wall_s, done.usage.peak_rss_mb
