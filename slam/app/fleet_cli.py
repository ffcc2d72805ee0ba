"""``python -m slam.fleet MANIFEST --out DIR``: many recordings in parallel on Ray, merged.

Examples::

    python -m slam.fleet drives.yaml --out fleet/                 # local Ray on this machine
    python -m slam.fleet drives.yaml --out fleet/ --address HOST:6379   # an existing cluster
    python -m slam.fleet --sweep sweep.yaml --out sweep/          # one recording, a grid of --set

Each manifest entry is one ``python -m slam.run`` call, run as a Ray task in a process of its own
with its share of the CPUs as its thread budget (``threads``), into ``DIR/runs/<name>/``, its
output in ``DIR/logs/<name>.log``. The runs that finished are merged into ``DIR/merged/`` by
``slam.merge``'s own code, in manifest order (the first finished run sets the frame). Called again
on the same ``DIR``, finished runs are reused and the rest redone; Ctrl-C or SIGTERM stops every
task cleanly first. A run that fails is reported in one line with its log and the others are
merged; the exit status is then 1. A sweep writes ``DIR/sweep.csv`` instead of merging.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import sys
import threading
from pathlib import Path

from slam.app.fleet_manifest import FleetRun, ManifestError, Sweep, load_manifest, load_sweep
from slam.app.fleet_plan import (
    FINISHED,
    RunTask,
    check_fleet_folder,
    discard,
    merge_levels,
    merge_memory_mb,
    merged_is_current,
    partial_path,
    plan_runs,
    thread_share,
)
from slam.app.fleet_progress import FleetProgress
from slam.app.signals import Terminated, handle_sigterm, restore_sigterm
from slam.assembly.config import OneLineParser, UsageError
from slam.assembly.datasets import DATASETS
from slam.run_folder.outputs import read_run_status

POLL_S = 1.0
MERGE_KEY = "merge:"
"""Prefix of a merge task's key (a run's key is its name, which cannot hold ':')."""
MERGE_DEFAULT = "global"
"""One merge of all runs: on 2 to 8 sessions it took less time and no more memory than pairwise
merges in a tree (benchmarks/results/fleet.md), and it is exactly ``slam.merge A B C ...``."""


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="python -m slam.fleet",
        description="Run many recordings in parallel on Ray and merge them into one map.",
    )
    parser.add_argument("manifest", nargs="?", type=Path, help="YAML list of runs")
    parser.add_argument("--sweep", type=Path, help="YAML: one run and a grid of --set values")
    parser.add_argument("--out", type=Path, required=True, help="fleet folder (new, or continued)")
    parser.add_argument(
        "--address",
        help="join this Ray cluster (default: RAY_ADDRESS, else a local Ray on this machine)",
    )
    parser.add_argument(
        "--num-cpus", type=int, help="CPUs of the local Ray (default: all; a cluster has its own)"
    )
    parser.add_argument(
        "--merge",
        choices=["global", "tree"],
        default=MERGE_DEFAULT,
        help="one merge of all runs, or pairwise merges in a tree",
    )
    parser.add_argument(
        "--record", action="store_true", help="write each run's and the merge's Rerun recording"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    return parser


def _resolved(run: FleetRun, base: Path) -> FleetRun:
    """Paths of the entry relative to the manifest's folder made absolute (a task may run
    elsewhere)."""
    update = {}
    for option in ("root", "config"):
        value = getattr(run, option)
        if value is not None:
            update[option] = (base / value.expanduser()).resolve()
    if run.sequence is not None and DATASETS[run.dataset].path_argument:
        update["sequence"] = str((base / Path(run.sequence).expanduser()).resolve())
    return run.model_copy(update=update)


_SIGTERM_SEEN = threading.Event()
"""Set by SIGTERM: Ray's waits may turn the :class:`Terminated` it raises into a plain
KeyboardInterrupt."""


def _on_sigterm(signum: int, frame: object) -> None:
    _SIGTERM_SEEN.set()
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # one is enough: let the cleanup finish
    raise Terminated()


def _catch_sigterm() -> None:
    """SIGTERM stops the fleet as Ctrl-C does (main thread only; elsewhere a no-op)."""
    _SIGTERM_SEEN.clear()
    with contextlib.suppress(ValueError):
        signal.signal(signal.SIGTERM, _on_sigterm)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    argv = list(argv if argv is not None else sys.argv[1:])
    previous = handle_sigterm()
    try:
        return _main(argv, "--debug" in argv)
    finally:
        restore_sigterm(previous)


def _main(argv: list[str], debug: bool) -> int:
    from slam.app import fleet_ray

    connected = False
    pool: fleet_ray.TaskPool | None = None
    out: Path | None = None
    try:
        args = build_parser().parse_args(argv)
        if (args.manifest is None) == (args.sweep is None):
            raise UsageError("give a MANIFEST or --sweep FILE (one of them)")
        out = args.out.expanduser().resolve()
        pool = fleet_ray.TaskPool(out / fleet_ray.STOP_FILE)
        source = args.manifest if args.sweep is None else args.sweep
        sweep: Sweep | None = None
        if args.sweep is not None:
            sweep = load_sweep(args.sweep)
            runs = [entry for entry, _ in sweep.combinations()]
        else:
            runs = load_manifest(args.manifest)
        runs = [_resolved(run, source.parent.resolve()) for run in runs]
        check_fleet_folder(out)
        pool.stop_file.unlink(missing_ok=True)  # left by a fleet that was killed while stopping
        fleet_ray.import_ray()
        connected = fleet_ray.connect(args.address, args.num_cpus)
        _catch_sigterm()  # ray.init installs its own SIGTERM handler, which aborts the driver
        size = fleet_ray.cluster_size()
        tasks = plan_runs(
            runs, out, thread_share(size.cpus, size.node_cpus, len(runs)), args.record
        )
        live = not args.no_progress and sys.stderr.isatty()
        progress = FleetProgress(total=len(tasks), live=live)
        try:
            finished = _run_all(tasks, pool, size, progress)
            if sweep is not None:
                return _write_sweep(sweep, tasks, finished, out, progress)
            merged_ok = _merge(tasks, finished, out, args, pool, size, progress)
        finally:
            progress.close()
    except KeyboardInterrupt as exc:
        if pool is not None:
            pool.stop_all()
        if out is not None:
            for leftover in out.glob("**/*.partial"):
                discard(leftover)
        where = f"; finished runs are kept in {out / 'runs'}" if out is not None else ""
        terminated = isinstance(exc, Terminated) or _SIGTERM_SEEN.is_set()
        cause = "terminated (SIGTERM)" if terminated else "interrupted"
        print(f"error: {cause}{where}; run the same command again to continue", file=sys.stderr)
        return 128 + signal.SIGTERM if terminated else 130
    except (UsageError, ManifestError, OSError) as exc:
        if debug:
            raise
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2 if isinstance(exc, UsageError) else 1
    finally:
        if connected:
            fleet_ray.disconnect()
    failed = len(tasks) - len(finished)
    print(
        f"{len(finished)} of {len(tasks)} runs finished"
        + (f", {failed} failed" if failed else "")
        + (f"; merged map in {out / 'merged'}" if merged_ok else "")
    )
    return 0 if failed == 0 and merged_ok else 1


def _finished(task: RunTask) -> bool:
    status = read_run_status(task.folder) if task.folder.is_dir() else None
    return status is not None and status.get("state") == FINISHED


def _done_line(task: RunTask) -> str:
    path = task.folder / "metrics.json"
    timing = json.loads(path.read_text()).get("timing", {}) if path.is_file() else {}
    wall, rate = timing.get("wall_s"), timing.get("frames_per_s")
    if wall is None or rate is None:
        return f"{task.run.name}: finished"
    return f"{task.run.name}: finished in {wall:.0f} s ({rate:.1f} frames/s)"


def _run_all(tasks: list[RunTask], pool, size, progress: FleetProgress) -> list[RunTask]:
    """Run every task not reused; returns the finished ones, in manifest order."""
    by_name = {task.run.name: task for task in tasks}
    for task in tasks:
        if task.reuse:
            progress.reuse(task.run.name)
            continue
        memory_mb = min(task.memory_mb, size.node_memory_mb or task.memory_mb)
        pool.submit(task.run.name, "slam.app.cli", task.argv, task.log, task.threads, memory_mb)
        progress.start(task.run.name, task.folder)
    while pool.pending:
        for name, outcome in pool.wait(POLL_S).items():
            task = by_name[name]
            if outcome.code == 0 and _finished(task):
                progress.end(name, True, _done_line(task))
            else:
                reason = outcome.error or f"exit status {outcome.code}"
                progress.end(name, False, f"error: run {name} failed: {reason}; log: {task.log}")
        progress.refresh()
    return [task for task in tasks if _finished(task)]


def _merge(tasks, finished, out: Path, args, pool, size, progress: FleetProgress) -> bool:
    """Merge the finished runs into ``out/merged`` (reused when it holds exactly them); returns
    whether a merged map of them exists. A merge needs two runs."""
    folders = [task.folder for task in finished]
    final = out / "merged"
    if len(folders) < 2:
        progress.say(f"error: nothing to merge: {len(folders)} run(s) finished")
        return False
    if merged_is_current(final, folders):
        progress.say(f"merged: {final} holds these runs already, reused")
        return True
    log = out / "logs" / "merge.log"
    for level in merge_levels(folders, out, args.merge == "tree"):
        steps = {
            f"{MERGE_KEY}{step.out}": step
            for step in level
            if not merged_is_current(step.out, step.runs)
        }
        cpus = max(1, min(size.node_cpus, size.cpus // max(1, len(steps))))
        for key, step in steps.items():
            partial = partial_path(step.out)
            discard(partial)
            argv = [*map(str, step.inputs), "--out", str(partial)]
            argv += [] if args.record else ["--no-viz"]
            memory_mb = min(merge_memory_mb(len(step.runs)), size.node_memory_mb or 1e12)
            pool.submit(key, "slam.app.merge_cli", argv, log, cpus, memory_mb)
        failure = ""
        while pool.pending:
            for key, outcome in pool.wait(POLL_S).items():
                step = steps[key]
                if outcome.code != 0:
                    failure = failure or outcome.error or f"exit status {outcome.code}"
                    continue
                discard(step.out)
                partial_path(step.out).rename(step.out)
        if failure:
            progress.say(f"error: merge failed: {failure}; log: {log}")
            return False
    progress.say(f"merged {len(folders)} runs into {final}")
    return True


def _write_sweep(sweep: Sweep, tasks, finished, out: Path, progress: FleetProgress) -> int:
    from common.atomic_io import write_text_atomic
    from slam.app.fleet_sweep import metric_row, sweep_csv

    done = {task.run.name for task in finished}
    rows = [
        (task.run.name, values, metric_row(task.folder, task.run.name in done))
        for task, (_, values) in zip(tasks, sweep.combinations(), strict=True)
    ]
    path = out / "sweep.csv"
    write_text_atomic(path, sweep_csv(rows, list(sweep.grid)))
    failed = len(tasks) - len(done)
    progress.say(f"{len(done)} of {len(tasks)} combinations finished; wrote {path}")
    return 0 if failed == 0 else 1
