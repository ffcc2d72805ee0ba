"""Where a run writes, checked before anything is read: its run folder (``--out`` or a new
time-stamped folder in ``output.root``) and its recording file (``--rrd``). A run never writes
into a folder holding files it did not create, never overwrites a file, and removes only a folder
it created and never started to fill."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
from datetime import datetime
from pathlib import Path

from common.atomic_io import write_problem
from slam.assembly.config import RunConfig, UsageError
from slam.assembly.datasets import DATASETS
from slam.run_folder.outputs import RUN_STATUS_FILE


def run_folder(cfg: RunConfig, args: argparse.Namespace) -> tuple[Path, bool]:
    """The run folder and whether this run creates it (only then may a failed run remove it).

    ``--out`` must name a new or an empty folder: writing into a folder that holds files would
    mix this run's outputs with stale ones.
    """
    if args.out is not None:
        folder = Path(args.out)
        if folder.exists():
            if not folder.is_dir():
                raise UsageError(f"--out {folder}: exists and is not a folder; pass a new folder")
            if any(folder.iterdir()):
                raise UsageError(
                    f"--out {folder}: folder is not empty; pass a new or empty folder (a run never "
                    "mixes its files with others)"
                )
            _require_writable(folder)
            return folder, False
        try:
            folder.mkdir(parents=True)
        except OSError as exc:
            raise UsageError(
                f"--out {folder}: cannot create the folder ({exc.strerror or exc}); pass a "
                "writable folder"
            ) from None
        return folder, True
    try:
        return _new_run_folder(cfg, args)
    except OSError as exc:
        raise UsageError(
            f"output.root {cfg.output.root}: cannot create a run folder in it "
            f"({exc.strerror or exc}); set output.root to a writable folder or pass --out DIR"
        ) from None


def rerun_switched_off() -> bool:
    """Rerun's documented switch ``RERUN=off`` (also 0, false, no) is set: its recording streams
    then drop everything, and setting sinks on one fails."""
    return os.environ.get("RERUN", "").strip().lower() in ("off", "0", "false", "no")


def check_recording_target(cfg: RunConfig, args: argparse.Namespace) -> None:
    """Refuse a recording file (``--rrd`` or ``viz.rrd_path``) that exists, even as a symlink
    (a run never overwrites a file, as ``--out`` never writes into a used folder), or that
    cannot be written, before anything is created."""
    path = cfg.viz.rrd_path
    if cfg.viz.mode not in ("rrd", "serve") or path is None:
        return
    option = "--rrd" if args.rrd is not None else "viz.rrd_path"
    path = Path(path).expanduser()
    if os.path.lexists(path):
        kind = "is a symlink" if path.is_symlink() else "exists"
        raise UsageError(
            f"{option} {path}: {kind}; pass a new file name (a run never overwrites a file)"
        )
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise UsageError(f"{option} {path}: {parent} is not a folder; pass a writable path")
    problem = write_problem(parent)
    if problem is not None:
        raise UsageError(f"{option} {path}: cannot write in {parent} ({problem}); pass another")


def _require_writable(folder: Path) -> None:
    problem = write_problem(folder)
    if problem is not None:
        raise UsageError(
            f"--out {folder}: cannot write in this folder ({problem}); pass a writable folder"
        )


def _new_run_folder(cfg: RunConfig, args: argparse.Namespace) -> tuple[Path, bool]:
    """A new time-stamped folder in ``output.root``."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    parts = (args.dataset, args.sequence)
    if DATASETS.get(args.dataset, DATASETS["demo"]).path_argument and args.sequence:
        parts = (args.dataset, Path(args.sequence).stem)
    name = cfg.output.run_name or "-".join(part for part in parts if part)
    cfg.output.root.mkdir(parents=True, exist_ok=True)
    suffix = 1
    folder = cfg.output.root / f"{name}-{stamp}"
    while True:
        try:
            folder.mkdir()
            return folder, True
        except FileExistsError:
            suffix += 1
            folder = cfg.output.root / f"{name}-{stamp}-{suffix}"


def discard_empty_run(folder: Path | None, created: bool) -> None:
    """Remove a run folder that this run created and that holds nothing but its log and config
    (the run never started). A folder the run did not create is never removed."""
    if folder is None or not created or not folder.is_dir():
        return
    started = ("run.log", "config.yaml", RUN_STATUS_FILE)
    if {p.name for p in folder.iterdir()} <= set(started):
        root = logging.getLogger()  # the log file goes: a later record must not reopen it
        for handler in list(root.handlers):
            if isinstance(handler, logging.FileHandler):
                root.removeHandler(handler)
                handler.close()
        for name in started:
            (folder / name).unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            folder.rmdir()
