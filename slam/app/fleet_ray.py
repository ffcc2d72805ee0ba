"""The fleet on Ray: start a local Ray or join a cluster, run each run and each merge as a Ray
task in a process of its own, and stop them.

The only module of the product besides the fleet CLI that imports ``ray`` (an optional extra,
``pip install -e ".[ray]"``); it is imported inside the functions that need it. A task calls the
command's own entry point (``slam.app.cli.main``, ``slam.app.merge_cli.main``) with the
command's arguments, its stdout and stderr appended to the task's log, so a fleet run is the
serial run. Tasks run once (``max_calls=1``: a fresh process each, which KISS-ICP's per-process
thread limit needs; ``max_retries=0``: a failure is reported, not repeated).

Tasks are stopped through a file, not ``ray.cancel``: a task cancelled that way still returns
normally once its command has handled the interrupt, and that reply can abort the driver inside
Ray (ray 2.60, ``task_manager.cc``: "Tried to complete task that was not pending"): 2 of 39
interrupted fleets of the test's three demo runs, on two busy cores.
"""

from __future__ import annotations

import os
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from slam.app.rerun_flush import leave_at_exit_if_given_up
from slam.assembly.config import UsageError
from slam.assembly.threads import machine_cores

INSTALL_HINT = 'pip install -e ".[ray]"'
OBJECT_STORE_MB = 200
"""Object store of a local Ray: tasks pass only arguments and exit statuses through it (Ray's
default, 30 % of the memory, would be taken from what the runs can be given)."""
STOP_GRACE_S = 15.0
"""How long a stopped task may take to end cleanly (write its status) before it is killed."""
STOP_FILE = ".stop"
"""In the fleet folder (storage every node sees): while it exists, every task interrupts itself
as Ctrl-C would, and a task that has not started returns at once."""
STOP_POLL_S = 0.2
"""How often a task looks for the stop file."""


def import_ray():
    """The ``ray`` module, or a :class:`UsageError` with the install hint."""
    try:
        import ray
    except ImportError:
        raise UsageError(f"the fleet runs on Ray, which is not installed; {INSTALL_HINT}") from None
    return ray


def connect(address: str | None, num_cpus: int | None) -> bool:
    """Join the Ray cluster at ``address`` (or ``RAY_ADDRESS``), else start a local Ray with
    ``num_cpus`` CPUs (default: this machine's). Returns whether this call connected (then the
    caller calls :func:`disconnect`); an already initialised Ray is used as it is."""
    ray = import_ray()
    if ray.is_initialized():
        return False
    address = address or os.environ.get("RAY_ADDRESS") or None
    common = {"logging_level": "ERROR", "log_to_driver": False}
    try:
        if address:
            ray.init(address=address, **common)
        else:
            ray.init(
                num_cpus=num_cpus or machine_cores(),
                include_dashboard=False,
                object_store_memory=OBJECT_STORE_MB * 2**20,
                **common,
            )
    except ConnectionError as exc:
        raise UsageError(
            f"--address {address}: cannot join the Ray cluster ({' '.join(str(exc).split())}); "
            "check the address (ray status on the head node prints it)"
        ) from None
    return True


def disconnect() -> None:
    """Leave Ray (a local Ray this process started stops)."""
    import_ray().shutdown()


@dataclass(frozen=True)
class ClusterSize:
    """CPUs and memory Ray can give tasks: in all, and on the largest node."""

    cpus: int
    node_cpus: int
    node_memory_mb: float


def cluster_size() -> ClusterSize:
    ray = import_ray()
    nodes = [node["Resources"] for node in ray.nodes() if node.get("Alive")]
    return ClusterSize(
        cpus=int(ray.cluster_resources().get("CPU", 1)),
        node_cpus=max((int(n.get("CPU", 0)) for n in nodes), default=1) or 1,
        node_memory_mb=max((n.get("memory", 0.0) for n in nodes), default=0.0) / 2**20,
    )


def _interrupt_when(stop_file: Path, done) -> None:
    """Send this process SIGINT once ``stop_file`` exists, unless ``done`` is set first."""
    import signal

    while not done.wait(STOP_POLL_S):
        if stop_file.exists():
            os.kill(os.getpid(), signal.SIGINT)
            return


def call_logged(module: str, argv: list[str], log: str, stop_file: str) -> tuple[int, str]:
    """Run ``module.main(argv)`` with stdout and stderr appended to ``log``; returns its exit
    status and its last ``error:`` line (without the prefix). Runs in the Ray task's process;
    ``stop_file`` appearing interrupts it (130 when it appeared before the start)."""
    import contextlib
    import importlib
    import signal
    import threading
    import traceback

    stop = Path(stop_file)
    if stop.exists():
        return 130, "stopped before it started"
    # the stop file interrupts with SIGINT: a driver started in the background (``cmd &``,
    # nohup) passes SIGINT ignored down to its workers, and the run could not be stopped cleanly
    with contextlib.suppress(ValueError):
        signal.signal(signal.SIGINT, signal.default_int_handler)
    done = threading.Event()
    watcher = threading.Thread(target=_interrupt_when, args=(stop, done), daemon=True)
    path = Path(log)
    path.parent.mkdir(parents=True, exist_ok=True)
    start = path.stat().st_size if path.exists() else 0
    with path.open("a") as handle:
        handle.write(f"$ python -m {module.removesuffix('.main')} {shlex.join(argv)}\n")
        handle.flush()
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(handle.fileno(), 1)
        os.dup2(handle.fileno(), 2)
        try:
            watcher.start()
            code = int(importlib.import_module(module).main(argv))
        except KeyboardInterrupt:  # the stop came after the command had stopped catching it
            code = 130
        except Exception:
            traceback.print_exc()
            code = 1
        finally:
            done.set()
            sys.stdout.flush()
            sys.stderr.flush()
            # Ray ends this worker after the task (one call each): a recording that was given
            # up would hold that exit for ever
            leave_at_exit_if_given_up()
    with path.open("rb") as handle:
        handle.seek(start)
        lines = handle.read().decode(errors="replace").splitlines()
    errors = [line.removeprefix("error: ") for line in lines if line.startswith("error: ")]
    if not errors and code != 0 and lines:
        errors = [lines[-1]]
    return code, errors[-1] if errors else ""


@dataclass
class Outcome:
    """How a task ended: exit status and its one-line error ("" when it succeeded)."""

    code: int
    error: str


@dataclass
class TaskPool:
    """Submitted tasks, keyed by the caller's names; :meth:`stop_all` stops them through
    ``stop_file`` (on storage every node sees)."""

    stop_file: Path
    pending: dict[Any, str] = field(default_factory=dict)
    """Ray object reference -> the task's key."""
    _task: Any = None

    def submit(
        self, key: str, module: str, argv: list[str], log: Path, cpus: int, memory_mb: float
    ) -> None:
        """Start ``module.main(argv)`` as a task needing ``cpus`` CPUs and ``memory_mb``."""
        if self._task is None:
            self._task = import_ray().remote(max_calls=1, max_retries=0)(call_logged)
        ref = self._task.options(
            num_cpus=cpus, memory=int(memory_mb * 2**20), name=f"slam-fleet:{key}"
        ).remote(module, argv, str(log), str(self.stop_file))
        self.pending[ref] = key

    def wait(self, timeout_s: float) -> dict[str, Outcome]:
        """The tasks that ended within ``timeout_s`` (at least one is waited for)."""
        ray = import_ray()
        if not self.pending:
            return {}
        ready, _ = ray.wait(list(self.pending), num_returns=1, timeout=timeout_s)
        if ready:  # collect every other one that is done too
            ready, _ = ray.wait(list(self.pending), num_returns=len(self.pending), timeout=0)
        ended = {}
        for ref in ready:
            key = self.pending.pop(ref)
            try:
                code, error = ray.get(ref)
            except ray.exceptions.RayError as exc:
                code, error = 1, f"Ray: {' '.join(str(exc).split())[:300]}"
            ended[key] = Outcome(code, error)
        return ended

    def stop_all(self) -> None:
        """Stop every task as Ctrl-C stops a run: create the stop file, wait up to
        :data:`STOP_GRACE_S` for the tasks to return, kill what is left, remove the file."""
        if not self.pending:
            return
        ray = import_ray()
        self.stop_file.touch()
        refs = list(self.pending)
        _, left = ray.wait(refs, num_returns=len(refs), timeout=STOP_GRACE_S)
        for ref in left:
            ray.cancel(ref, force=True)
        self.pending.clear()
        self.stop_file.unlink(missing_ok=True)
