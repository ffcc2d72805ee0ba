"""Measured child processes: a Python function in a fresh interpreter, or a command.

Each measurement runs in its own process so that its peak resident memory is its own. Both
report wall time, CPU time (user + system, all threads) and peak RSS of the child alone: on
Linux a process's ``ru_maxrss`` includes the high-water mark of the process that forked it
(carried across fork and exec), so a function's peak is read from its own address space
(``VmHWM``) and a command is started by a small wrapper process (:class:`MeasuredCommand`).
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks.harness.machine import proc_memory_kib
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
    peak_mb = proc_memory_kib()["VmHWM"] / 1024
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


_WRAPPER = """
import os, signal, subprocess, sys
result = os.fdopen(int(sys.argv[1]), "w", buffering=1)
try:
    command = subprocess.Popen(sys.argv[2:])
except OSError as error:
    print("error", error.errno, file=result)
    sys.exit(1)
signal.signal(signal.SIGINT, signal.SIG_IGN)
print(command.pid, file=result)
_, status, usage = os.wait4(command.pid, 0)
print(status, usage.ru_maxrss, usage.ru_utime + usage.ru_stime, file=result)
"""
"""``python -I -c _WRAPPER FD COMMAND...``: starts ``COMMAND`` (which inherits its streams), writes
the command's pid to file descriptor ``FD``, waits for it and writes its wait status, peak RSS
(KiB) and CPU seconds. It imports nothing but a few standard modules, so its high-water mark,
which the command inherits, is small. Ctrl-C reaches the command itself; the wrapper waits."""


@dataclass
class Finished:
    """How a measured command ended: exit code (negative: the signal that ended it), CPU time
    (user + system, its waited-for children included) and its own peak RSS."""

    returncode: int
    cpu_s: float
    peak_rss_mb: float


class MeasuredCommand:
    """``command`` started through :data:`_WRAPPER`, so that the peak RSS measured is its own,
    not that of this (possibly large) process. ``streams`` (``stdin``, ``stdout``, ``stderr``,
    ``text``) are ``subprocess.Popen``'s and reach the command unchanged; ``process`` is the
    wrapper (its ``stdout``/``stderr`` pipes are the command's), ``pid`` the command's own."""

    def __init__(
        self, command: list[str], *, cwd: Path, env: dict[str, str] | None = None, **streams
    ):
        read_fd, write_fd = os.pipe()
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-I", "-c", _WRAPPER, str(write_fd), *command],
                cwd=cwd,
                env=env,
                pass_fds=(write_fd,),
                **streams,
            )
        except BaseException:
            os.close(read_fd)
            raise
        finally:
            os.close(write_fd)
        self.command = command
        self.finished: Finished | None = None
        self._result = os.fdopen(read_fd)
        started = self._said()
        if started[0] == "error":
            self.process.wait()
            self._result.close()
            errno = int(started[1])
            raise OSError(errno, os.strerror(errno), command[0])
        self.pid = int(started[0])

    def poll(self) -> Finished | None:
        """How the command ended, or None while it runs."""
        if self.finished is None and self.process.poll() is not None:
            status, peak_kib, cpu_s = self._said()
            self._result.close()
            self.finished = Finished(
                os.waitstatus_to_exitcode(int(status)), float(cpu_s), int(peak_kib) / 1024
            )
        return self.finished

    def wait(self) -> Finished:
        """Wait for the command to end; how it ended."""
        self.process.wait()
        return self.poll()

    def kill(self) -> None:
        """SIGKILL the command itself (it ends with -9), unless it has already been waited for
        (its wrapper, which reaps it, then exits at once)."""
        if self.process.poll() is None:
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def _said(self) -> list[str]:
        """The wrapper's next line, split; a wrapper that ended without writing it is an
        error."""
        said = self._result.readline().split()
        if not said:
            self._result.close()
            raise RuntimeError(
                f"the process measuring {self.command[0]} ended ({self.process.wait()}) "
                "without saying how the command did; see its stderr"
            )
        return said


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
    """Run ``command`` as a :class:`MeasuredCommand`; its output goes to ``log_file`` (else it
    is captured), ``on_poll(pid)`` is called with the command's pid about once a second, and
    past ``timeout_s`` it is killed (status -9)."""
    start = time.perf_counter()
    stream = open(log_file, "w") if log_file is not None else subprocess.PIPE
    try:
        child = MeasuredCommand(
            command, cwd=cwd, env=env, stdout=stream, stderr=subprocess.STDOUT, text=True
        )
        if log_file is None:
            # a reader thread keeps the pipe drained while the command is polled
            output: list[str] = []
            import threading

            reader = threading.Thread(target=lambda: output.append(child.process.stdout.read()))
            reader.start()
        while (finished := child.poll()) is None:
            if time.perf_counter() - start > timeout_s:
                child.kill()
            if on_poll is not None:
                on_poll(child.pid)
            time.sleep(0.5)
        text = ""
        if log_file is None:
            reader.join()
            text = "".join(output)
    finally:
        if log_file is not None:
            stream.close()
    cost = Usage(time.perf_counter() - start, finished.cpu_s, finished.peak_rss_mb)
    return CommandResult(finished.returncode, text, cost)


def run_module(module: str, args: list[str], log_file: Path) -> tuple[float, float]:
    """``python -m module args`` in this tree, its output in ``log_file``: (wall s, peak RSS
    MB); a failure raises, naming the log."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    done = run_command([sys.executable, "-m", module, *args], cwd=REPO, env=env, log_file=log_file)
    if done.returncode != 0:
        raise RuntimeError(f"{module} {' '.join(args)} failed; see {log_file}")
    return done.usage.wall_s, done.usage.peak_rss_mb
