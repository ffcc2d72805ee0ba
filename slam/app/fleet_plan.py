"""What a fleet has to do, without Ray: the run command of each manifest entry, its share of the
CPUs and its memory, which run folders are finished and reused, and the merge's inputs.

A fleet folder ``DIR`` holds ``runs/<name>/`` (normal run folders), ``logs/<name>.log`` (each
task's output), ``merged/`` (what ``slam.merge`` writes), ``merge_tree/`` (the intermediate
merges of ``--merge tree``) and ``fleet.json``, the manifest entries
its run folders were made from. A run folder is reused when its ``run_status.json`` says
``finished`` and ``fleet.json`` holds the same entry; any other run folder is removed and the run
redone. ``DIR`` must be new, empty or a fleet folder: the fleet never removes what it did not make.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.atomic_io import write_text_atomic
from slam.app.fleet_manifest import FleetRun
from slam.assembly.config import UsageError
from slam.run_folder.outputs import read_run_status

STATE_FILE = "fleet.json"
FINISHED = "finished"

LIDAR_DATASETS = frozenset({"kitti", "generated-lidar", "lidar"})
TASK_MEMORY_MB = {"lidar": 1200, "rgbd": 800}
"""Memory Ray reserves for one run of each sensor kind: the measured peak RSS with a margin.
LiDAR: about 1 GB (MulRan keyframes 1066 MB, README "Real scans"); RGB-D: ``slam.run demo``
(240 frames, one thread) 663 MB before its mesh is scored."""
SCORING_MEMORY_MB = 900
"""Added for a run that scores its mesh against a ground-truth mesh (generated data, Replica)
with ``output.mesh_samples`` above 0: scoring took ``slam.run demo`` from 663 to 1489 MB."""
DATASETS_WITH_GT_MESH = frozenset({"demo", "generated-lidar", "replica"})

MERGE_MEMORY_BASE_MB = 900
"""Memory Ray reserves for a merge: 882 MB measured merging three 45-frame windows of the room
at the default settings, 475-532 MB for 2-8 of the benchmark's quick windows
(``benchmarks/results/fleet.md``); plus :data:`MERGE_MEMORY_MB_PER_SESSION` a session."""
MERGE_MEMORY_MB_PER_SESSION = 100


def sensor_of(run: FleetRun) -> str:
    """``lidar`` or ``rgbd``: the kind of recording the entry's dataset holds."""
    return "lidar" if run.dataset in LIDAR_DATASETS else "rgbd"


def run_memory_mb(run: FleetRun) -> int:
    """Memory Ray reserves for the run of an entry."""
    scored = run.dataset in DATASETS_WITH_GT_MESH and run.set_items().get("output.mesh_samples", 1)
    return TASK_MEMORY_MB[sensor_of(run)] + (SCORING_MEMORY_MB if scored else 0)


def set_argument(key: str, value: Any) -> str:
    """``KEY=VALUE`` for ``--set``, the value written as YAML (what ``--set`` parses)."""
    import yaml

    if isinstance(value, str) and _reads_back(value):
        return f"{key}={value}"
    text = yaml.safe_dump(value, default_flow_style=True, width=10**9)
    return f"{key}={text.removesuffix('...' + chr(10)).strip()}"


def _reads_back(text: str) -> bool:
    """Whether ``--set`` reads ``text`` as this very string."""
    import yaml

    try:
        return yaml.safe_load(text) == text
    except yaml.YAMLError:
        return False


def run_argv(run: FleetRun, folder: Path, threads: int, record: bool) -> list[str]:
    """The ``python -m slam.run`` arguments of one entry; ``threads`` is used unless the entry
    sets ``threads`` itself."""
    argv = [run.dataset] + ([run.sequence] if run.sequence is not None else [])
    for option in ("root", "config", "frames", "odometry", "device", "dataloader", "topic"):
        value = getattr(run, option)
        if value is not None:
            argv += [f"--{option}", str(value)]
    items = run.set_items()
    items.setdefault("threads", threads)
    for key, value in items.items():
        argv += ["--set", set_argument(key, value)]
    argv += ([] if record else ["--no-viz"]) + ["--no-progress", "--out", str(folder)]
    return argv


def run_threads(run: FleetRun, share: int) -> int:
    """The thread budget a run gets: its own ``threads`` setting, else ``share``."""
    own = run.set_items().get("threads")
    return int(own) if isinstance(own, int) and own > 0 else share


def thread_share(total_cpus: int, node_cpus: int, runs: int) -> int:
    """CPUs per run: the cluster's CPUs split between the runs that can go at once, at most one
    node's (a task runs on one node), at least one."""
    at_once = max(1, min(runs, total_cpus))
    return max(1, min(node_cpus, total_cpus // at_once))


@dataclass
class RunTask:
    """One manifest entry, ready to submit (or reused)."""

    run: FleetRun
    argv: list[str]
    folder: Path
    log: Path
    threads: int
    memory_mb: int
    reuse: bool


def _spec(run: FleetRun, record: bool) -> dict[str, Any]:
    """What makes a run folder the result of an entry (the thread share does not: it only
    changes the last digits of a multi-threaded LiDAR run)."""
    return {**run.model_dump(mode="json", by_alias=True), "record": record}


def check_fleet_folder(out: Path) -> None:
    """``out`` is new, empty or a fleet folder; else a :class:`UsageError`."""
    if not out.exists():
        return
    if not out.is_dir():
        raise UsageError(f"--out {out}: exists and is not a folder; pass a new folder")
    if any(out.iterdir()) and not (out / STATE_FILE).is_file():
        raise UsageError(
            f"--out {out}: folder is not empty and holds no {STATE_FILE}; pass a new folder or "
            "the folder of an earlier fleet to continue it"
        )


def plan_runs(runs: list[FleetRun], out: Path, share: int, record: bool) -> list[RunTask]:
    """The tasks of ``runs`` in ``out``: finished run folders of the same entry are reused, any
    other folder of an entry is removed (the run is redone). Writes ``fleet.json``."""
    check_fleet_folder(out)
    state_path = out / STATE_FILE
    previous: dict[str, Any] = {}
    if state_path.is_file():
        previous = json.loads(state_path.read_text()).get("runs", {})
    tasks = []
    for run in runs:
        folder = out / "runs" / run.name
        status = read_run_status(folder) if folder.is_dir() else None
        reuse = (
            status is not None
            and status.get("state") == FINISHED
            and previous.get(run.name) == _spec(run, record)
        )
        if folder.exists() and not reuse:
            shutil.rmtree(folder)
        threads = run_threads(run, share)
        tasks.append(
            RunTask(
                run=run,
                argv=run_argv(run, folder, threads, record),
                folder=folder,
                log=out / "logs" / f"{run.name}.log",
                threads=threads,
                memory_mb=run_memory_mb(run),
                reuse=reuse,
            )
        )
    (out / "runs").mkdir(parents=True, exist_ok=True)
    (out / "logs").mkdir(parents=True, exist_ok=True)
    state = {"runs": {**previous, **{run.name: _spec(run, record) for run in runs}}}
    write_text_atomic(state_path, json.dumps(state, indent=2) + "\n")
    return tasks


def merge_memory_mb(sessions: int) -> int:
    """Memory Ray reserves for a merge of ``sessions`` run folders."""
    return MERGE_MEMORY_BASE_MB + MERGE_MEMORY_MB_PER_SESSION * sessions


@dataclass
class MergeStep:
    """One ``slam.merge`` call: its inputs (in order), its output folder and the run folders
    its output covers (what its ``sessions.csv`` lists)."""

    inputs: list[Path]
    out: Path
    runs: list[Path]


def merge_levels(folders: list[Path], out: Path, tree: bool) -> list[list[MergeStep]]:
    """The merges that join ``folders`` into ``out / "merged"``, level by level (the merges of a
    level are independent). Global: one merge of all. Tree: neighbours in pairs (an odd one out
    goes up alone), then the pairs' results in pairs, so the order of the frames is kept."""
    final = out / "merged"
    if not tree or len(folders) <= 2:
        return [[MergeStep(list(folders), final, list(folders))]]
    levels: list[list[MergeStep]] = []
    current = list(folders)
    covers = {folder: [folder] for folder in folders}
    depth = 0
    while len(current) > 1:
        depth += 1
        steps, next_level = [], []
        for k in range(0, len(current), 2):
            pair = current[k : k + 2]
            if len(pair) == 1:
                next_level.append(pair[0])
                continue
            last = len(current) <= 2
            target = final if last else out / "merge_tree" / f"level{depth}-{k // 2}"
            covers[target] = covers[pair[0]] + covers[pair[1]]
            steps.append(MergeStep(pair, target, covers[target]))
            next_level.append(target)
        levels.append(steps)
        current = next_level
    return levels


def merged_is_current(merged: Path, folders: list[Path]) -> bool:
    """Whether ``merged`` is a finished merge of exactly ``folders``, in this order (a merge is
    written under another name and renamed, so a folder there is complete)."""
    import csv

    sessions = merged / "sessions.csv"
    if not sessions.is_file() or not (merged / "metrics.json").is_file():
        return False
    with sessions.open(newline="") as handle:
        names = [row["run_folder"] for row in csv.DictReader(handle)]
    return names == [str(folder) for folder in folders]


def partial_path(target: Path) -> Path:
    """Where a merge into ``target`` is written before it is renamed to ``target``."""
    return target.with_name(target.name + ".partial")


def discard(folder: Path) -> None:
    """Remove a folder the fleet wrote (a stale or partial merge)."""
    if folder.exists():
        shutil.rmtree(folder)
