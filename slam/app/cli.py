"""``python -m slam.run DATASET [SEQUENCE] ...``: the command line of a run.

Examples::

    python -m slam.run demo                                  # generated RGB-D room, no data needed
    python -m slam.run generated-lidar                        # generated LiDAR street loop
    python -m slam.run kitti 00 --root /data/kitti --frames 0:1000
    python -m slam.run icl lr-kt3 --root /data/icl --no-viz
    python -m slam.run 7scenes seq-01 --root /data/7scenes/redkitchen --set submaps.max_frames=20
    python -m slam.run lidar recording.bag --dataloader rosbag       # any kiss_icp dataloader
    python -m slam.run lidar scans/ --dataloader generic --serve     # headless: web viewer
    python -m slam.run rgbd my_rgbd/                                 # rgb/, depth/, intrinsics.txt

This module turns the arguments into a validated :class:`~slam.assembly.config.RunConfig` and a run
folder (:mod:`slam.app.run_targets`), calls :func:`slam.app.runner.execute`, and reports errors in
one line. ``--out DIR`` must name a new or empty folder: a run never writes into, or deletes, a
folder holding anything it did not create. Bad input (unknown dataset, missing root, bad frame
range, bad config key) ends the run with one line on stderr and a nonzero exit status.
"""

from __future__ import annotations

import argparse
import errno
import logging
import os
import signal
import sys
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from frontends.errors import DatasetError, OdometryProcessError
from mapping.errors import MapFileError, WeightsFileError
from slam.app.run_targets import (
    check_recording_target,
    discard_empty_run,
    rerun_switched_off,
    run_folder,
)
from slam.app.signals import Terminated, handle_sigterm, restore_sigterm
from slam.app.summary import summary_lines
from slam.assembly.config import (
    ConfigError,
    OneLineParser,
    RunConfig,
    UsageError,
    default_config_path,
    describe_validation_error,
    load_run_config,
    set_nested,
    set_origins,
    set_overrides,
)
from slam.assembly.datasets import DATASETS, DatasetEntry
from slam.assembly.error_line import error_line
from slam.run_folder.outputs import SESSION_FOLDER


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="python -m slam.run",
        description="SLAM with loop closure and a remapped neural implicit map.",
        epilog="datasets: " + ", ".join(DATASETS),
    )
    parser.add_argument("dataset", help="one of: " + ", ".join(DATASETS))
    parser.add_argument(
        "sequence",
        nargs="?",
        help="sequence name (e.g. 00, lr-kt3, seq-01); for lidar and rgbd: the recording's path",
    )
    parser.add_argument("--root", type=Path, help="dataset root folder (cache folder for demo)")
    parser.add_argument("--config", type=Path, help="YAML config (default: configs/<dataset>.yaml)")
    parser.add_argument("--frames", help="frame range A:B[:STEP] (Python slice syntax)")
    parser.add_argument("--odometry", choices=["gt", "kiss-icp", "rgbd"], help="odometry method")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], help="torch device of the map")
    parser.add_argument(
        "--dataloader",
        help="lidar: kiss_icp dataloader (generic, rosbag, mcap, ouster, nuscenes, mulran, ncd, "
        "helipr, boreas, apollo, nclt, kitti, kitti_raw, npy)",
    )
    parser.add_argument("--topic", help="lidar: PointCloud2 topic of a bag or MCAP file")
    viz = parser.add_mutually_exclusive_group()
    viz.add_argument("--rrd", type=Path, help="write the Rerun recording to this file")
    viz.add_argument("--spawn", action="store_true", help="stream to a newly spawned viewer")
    viz.add_argument("--connect", metavar="URL", help="stream to a running viewer")
    viz.add_argument(
        "--serve",
        action="store_true",
        help="serve the live run to Rerun's web viewer over HTTP (prints the URL; also writes "
        "the .rrd); ports: viz.serve_web_port, viz.serve_grpc_port",
    )
    viz.add_argument("--no-viz", action="store_true", help="record nothing")
    parser.add_argument("--out", type=Path, help="run folder (default: outputs/<name>-<time>)")
    parser.add_argument(
        "--map",
        type=Path,
        metavar="RUN_DIR",
        help="continue the map of this run folder: the run is relocalised in it and the output "
        "is a merged run (the run alone goes to OUT/session)",
    )
    parser.add_argument(
        "--localise",
        action="store_true",
        help="with --map: only localise in the map (poses in its frame with a status per frame; "
        "no map, mesh or merge is written)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set loop_closure.enabled=false (repeatable)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("-v", "--verbose", action="store_true", help="log INFO to stderr")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    return parser


def parse_frames(text: str, option: str = "--frames") -> slice:
    """``"A:B[:STEP]"`` (parts may be empty) as a slice; a bad range is a :class:`UsageError`
    naming ``option`` (the argument or config key the range came from)."""
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise UsageError(f"{option} '{text}': expected A:B or A:B:STEP, e.g. 0:500 or ::2")
    try:
        values = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise UsageError(f"{option} '{text}': A, B and STEP must be integers") from None
    start, stop = values[0], values[1]
    step = values[2] if len(values) == 3 else None
    if step is not None and step <= 0:
        raise UsageError(f"{option} '{text}': STEP must be positive")
    if (start is not None and start < 0) or (stop is not None and stop < 0):
        raise UsageError(f"{option} '{text}': A and B must not be negative")
    if start is not None and stop is not None and stop <= start:
        raise UsageError(f"{option} '{text}': B must be greater than A")
    return slice(start, stop, step)


def cli_overrides(args: argparse.Namespace, entry: DatasetEntry) -> dict[str, Any]:
    """The config values given on the command line, as a nested mapping."""
    overrides = set_overrides(args.set)
    set_nested(overrides, "source.dataset", entry.source)
    if entry.path_argument and args.sequence is not None:
        path = Path(args.sequence).expanduser()
        if entry.source == "lidar":
            set_nested(overrides, "source.root", str(path))
        else:  # an RGB-D folder: its parent is the root, its name the sequence
            resolved = path.resolve()
            set_nested(overrides, "source.root", str(resolved.parent))
            set_nested(overrides, "source.sequence", resolved.name)
    elif args.sequence is not None:
        set_nested(overrides, "source.sequence", args.sequence)
    if args.root is not None:
        set_nested(overrides, "source.root", str(args.root))
    if args.dataloader is not None:
        set_nested(overrides, "source.lidar.dataloader", args.dataloader)
    if args.topic is not None:
        set_nested(overrides, "source.lidar.topic", args.topic)
    if args.frames is not None:
        parse_frames(args.frames)
        set_nested(overrides, "source.frames", args.frames)
    if args.odometry is not None:
        set_nested(overrides, "odometry.method", args.odometry)
    if args.device is not None:
        set_nested(overrides, "mapping.device", args.device)
    if args.no_viz:
        set_nested(overrides, "viz.mode", "none")
    elif args.spawn:
        set_nested(overrides, "viz.mode", "spawn")
    elif args.serve:
        set_nested(overrides, "viz.mode", "serve")
    elif args.connect:
        set_nested(overrides, "viz.mode", "connect")
        set_nested(overrides, "viz.connect_url", args.connect)
    elif args.rrd is not None:
        set_nested(overrides, "viz.mode", "rrd")
        set_nested(overrides, "viz.rrd_path", str(args.rrd))
    return overrides


def resolve_config(args: argparse.Namespace) -> tuple[DatasetEntry, RunConfig]:
    """Dataset entry and validated config from the command line."""
    entry = DATASETS.get(args.dataset)
    if entry is None:
        raise UsageError(f"unknown dataset '{args.dataset}'; choose one of: {', '.join(DATASETS)}")
    if entry.path_argument and args.sequence is None:
        raise UsageError(
            f"{args.dataset} needs the recording's PATH, e.g. python -m slam.run {args.dataset} "
            + ("scans/ --dataloader generic" if entry.source == "lidar" else "my_rgbd_folder/")
        )
    if (args.dataloader is not None or args.topic is not None) and entry.source != "lidar":
        raise UsageError("--dataloader and --topic apply to the lidar dataset only")
    if entry.needs_sequence and args.sequence is None:
        raise UsageError(
            f"{args.dataset} needs a SEQUENCE, e.g. python -m slam.run {args.dataset} "
            f"{'00' if args.dataset == 'kitti' else '<name>'} --root DIR"
        )
    if not entry.needs_sequence and args.sequence is not None:
        raise UsageError(f"{args.dataset} takes no SEQUENCE (got '{args.sequence}')")
    if entry.needs_root and args.root is None and args.config is None:
        raise UsageError(f"{args.dataset} needs --root DIR, the folder holding the dataset")
    path = args.config if args.config is not None else default_config_path(entry.config)
    cfg = load_run_config(path, cli_overrides(args, entry), set_origins(args.set))
    if entry.path_argument and not Path(cfg.source.root).expanduser().exists():
        raise FileNotFoundError(f"{cfg.source.root} does not exist; pass the recording's path")
    if entry.needs_root:
        root = cfg.source.root
        if root is None:
            raise UsageError(f"{args.dataset} needs --root DIR, the folder holding the dataset")
        if not Path(root).expanduser().is_dir():
            raise FileNotFoundError(f"dataset root {root} does not exist; pass --root DIR")
    if cfg.source.frames is not None and args.frames is None:
        origin = set_origins(args.set).get("source.frames", f"source.frames of {path}")
        parse_frames(cfg.source.frames, origin)
    return entry, cfg


def _setup_logging(log_file: Path, verbose: bool) -> None:
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    for handler in list(root.handlers):
        root.removeHandler(handler)
    console = logging.StreamHandler(sys.stderr)
    console.setLevel(logging.INFO if verbose else logging.WARNING)
    console.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root.addHandler(console)
    log_file.parent.mkdir(parents=True, exist_ok=True)
    file_handler = logging.FileHandler(log_file)
    file_handler.setLevel(logging.INFO)
    file_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root.addHandler(file_handler)


USER_ERRORS: tuple[type[BaseException], ...] = (
    UsageError,
    ConfigError,
    DatasetError,
    OdometryProcessError,
    MapFileError,
    WeightsFileError,
    OSError,
    ValidationError,
)
"""Errors caused by the user's input or environment (a missing or unwritable file, a full disk):
reported in one line, without a traceback."""

_OS_HINTS = {
    errno.ENOSPC: "free some space or pass --out on another disk",
    errno.EDQUOT: "free some space or pass --out on another disk",
    errno.EROFS: "the file system is read-only; pass --out on a writable one",
    errno.EACCES: "check the permissions or pass another --out",
    errno.EPERM: "check the permissions or pass another --out",
}


def _one_line(exc: BaseException, folder: Path | None = None) -> str:
    if isinstance(exc, ValidationError):
        return describe_validation_error(exc, "config", model=None)
    return error_line(exc, _OS_HINTS, folder)


def normalize_argv(argv: list[str]) -> list[str]:
    """``--frames -5:10`` as ``--frames=-5:10``: argparse would take ``-5:10`` for an option
    and answer "expected one argument" instead of explaining the range."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        if argv[i] == "--frames" and i + 1 < len(argv) and argv[i + 1].startswith("-"):
            out.append(f"--frames={argv[i + 1]}")
            i += 2
            continue
        out.append(argv[i])
        i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    argv = normalize_argv(list(argv if argv is not None else sys.argv[1:]))
    debug = "--debug" in argv
    previous_sigterm = handle_sigterm()
    try:
        return _main(argv, debug)
    finally:
        restore_sigterm(previous_sigterm)


def _main(argv: list[str], debug: bool) -> int:
    folder: Path | None = None
    created = False
    try:
        args = build_parser().parse_args(argv)
        entry, cfg = resolve_config(args)
        previous = continued = None
        if args.localise and args.map is None:
            raise UsageError("--localise needs --map RUN_DIR, the map to localise in")
        if args.map is not None:  # refuse a map the run cannot join before reading a frame
            from slam.app.continue_map import continued_map, load_map_folder

            previous = load_map_folder(args.map, cfg)
            continued = continued_map(previous, args.map, cfg, args.localise)
        check_recording_target(cfg, args)
        folder, created = run_folder(cfg, args)
        _setup_logging(folder / "run.log", args.verbose)
        if continued is not None and continued.localise_only:  # decoded before the run's log
            seconds = continued.relocaliser.decode_seconds
            logging.getLogger("slam.run").info("decoded the map's surfaces in %.1f s", seconds)
        if cfg.viz.mode != "none" and rerun_switched_off():
            logging.getLogger("slam.run").warning(
                "RERUN=%s switches Rerun off: recording nothing, as with --no-viz",
                os.environ.get("RERUN"),
            )
            cfg.viz.mode = "none"
        from slam.app.runner import execute

        metrics = execute(
            entry,
            cfg,
            folder if previous is None or args.localise else folder / SESSION_FOLDER,
            progress=not args.no_progress,
            announce=lambda line: print(line, file=sys.stderr, flush=True),
            check_config=None if previous is None else _map_check(previous, args.map),
            continued=continued,
        )
        if args.localise:
            from slam.app.continue_map import check_placed

            check_placed(metrics, args.map, folder)
        if previous is not None and not args.localise:
            from slam.app.continue_map import merge_into

            merged = merge_into(
                previous, args.map, folder / SESSION_FOLDER, folder, cfg.viz.mode != "none", cfg
            )
            metrics["continued_map"] = merged
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, Terminated)
        discard_empty_run(folder, created)
        where = f"; partial outputs in {folder}" if folder is not None and folder.is_dir() else ""
        cause = "terminated (SIGTERM)" if terminated else "interrupted"
        print(f"error: {cause}{where}", file=sys.stderr)
        return 128 + signal.SIGTERM if terminated else 130
    except USER_ERRORS as exc:
        if debug:
            raise
        discard_empty_run(folder, created)
        status = 2 if isinstance(exc, UsageError) else 1
        print(f"error: {_one_line(exc, folder)}", file=sys.stderr)
        return status
    if not metrics.get("summary_announced"):
        for line in summary_lines(metrics):
            print(line)
    merged = metrics.get("continued_map")
    if merged is not None:
        line = (
            f"continued {args.map}: {merged['inter_session_loops_kept']} inter-session loops kept"
        )
        if "combined_ate_rmse_m" in merged:
            line += f", combined ATE {100 * merged['combined_ate_rmse_m']:.2f} cm"
        print(f"{line}; merged run in {folder} (this run alone in {folder / SESSION_FOLDER})")
    return 0


def _map_check(previous, map_folder: Path):
    """The ``--map`` check of a config whose voxel size came from the first scan."""
    from slam.app.continue_map import check_config

    return lambda cfg: check_config(previous[1], cfg, map_folder, before_first_scan=False)


if __name__ == "__main__":
    sys.exit(main())
