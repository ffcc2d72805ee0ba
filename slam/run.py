"""``python -m slam.run DATASET [SEQUENCE] ...``: run the whole pipeline on a sequence.

Examples::

    python -m slam.run demo                                  # generated RGB-D room, no data needed
    python -m slam.run generated-lidar                        # generated LiDAR street loop
    python -m slam.run kitti 00 --root /data/kitti --frames 0:1000
    python -m slam.run icl lr-kt3 --root /data/icl --no-viz
    python -m slam.run 7scenes seq-01 --root /data/7scenes/redkitchen --set submaps.max_frames=20
    python -m slam.run lidar recording.bag --dataloader rosbag       # any kiss_icp dataloader
    python -m slam.run lidar scans/ --dataloader generic --serve     # headless: web viewer
    python -m slam.run rgbd my_rgbd/                                 # rgb/, depth/, intrinsics.txt

The run folder (default ``outputs/<dataset>-<sequence>-<time>``) receives the resolved config,
both trajectories, ``loops.csv``, ``mesh.ply``, the map, ``metrics.json``, ``run.log`` and the
Rerun recording. ``--out DIR`` must name a new or empty folder: a run never writes into, or
deletes, a folder holding anything it did not create. Bad input (unknown dataset, missing root,
bad frame range, bad config key) ends the run with one line on stderr and a nonzero exit status.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from frontends.errors import DatasetError
from mapping.errors import MapFileError
from slam.config import (
    ConfigError,
    RunConfig,
    default_config_path,
    describe_validation_error,
    load_run_config,
)

logger = logging.getLogger("slam.run")


@dataclass(frozen=True)
class DatasetEntry:
    """A dataset name of the command line: its source, default config and whether it needs data.

    ``path_argument``: the positional argument is the recording's path (not a sequence name).
    """

    source: str
    config: str
    needs_root: bool
    needs_sequence: bool
    path_argument: bool = False


DATASETS: dict[str, DatasetEntry] = {
    "kitti": DatasetEntry("kitti", "kitti", True, True),
    "icl": DatasetEntry("icl", "icl", True, True),
    "tum": DatasetEntry("tum", "tum", True, True),
    "replica": DatasetEntry("replica", "replica", True, True),
    "7scenes": DatasetEntry("7scenes", "7scenes", True, True),
    "demo": DatasetEntry("generated", "demo", False, False),
    "generated-lidar": DatasetEntry("generated", "generated-lidar", False, False),
    "lidar": DatasetEntry("lidar", "lidar", False, True, path_argument=True),
    "rgbd": DatasetEntry("tum", "tum", False, True, path_argument=True),
}


class UsageError(ValueError):
    """Bad command-line input (exit status 2)."""


class _OneLineParser(argparse.ArgumentParser):
    """argparse whose errors are a single line (no usage block)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{message} (see python -m slam.run --help)")


def build_parser() -> argparse.ArgumentParser:
    parser = _OneLineParser(
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


def parse_frames(text: str) -> slice:
    """``"A:B[:STEP]"`` (parts may be empty) as a slice; a bad range is a :class:`UsageError`."""
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise UsageError(f"--frames '{text}': expected A:B or A:B:STEP, e.g. 0:500 or ::2")
    try:
        values = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise UsageError(f"--frames '{text}': A, B and STEP must be integers") from None
    start, stop = values[0], values[1]
    step = values[2] if len(values) == 3 else None
    if step is not None and step <= 0:
        raise UsageError(f"--frames '{text}': STEP must be positive")
    if (start is not None and start < 0) or (stop is not None and stop < 0):
        raise UsageError(f"--frames '{text}': A and B must not be negative")
    if start is not None and stop is not None and stop <= start:
        raise UsageError(f"--frames '{text}': B must be greater than A")
    return slice(start, stop, step)


def _set_nested(target: dict[str, Any], dotted: str, value: Any) -> None:
    keys = dotted.split(".")
    node = target
    for key in keys[:-1]:
        node = node.setdefault(key, {})
        if not isinstance(node, dict):
            raise UsageError(f"--set {dotted}: '{key}' is not a config section")
    node[keys[-1]] = value


def cli_overrides(args: argparse.Namespace, entry: DatasetEntry) -> dict[str, Any]:
    """The config values given on the command line, as a nested mapping."""
    import yaml

    overrides: dict[str, Any] = {}
    for item in args.set:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--set '{item}': expected KEY=VALUE, e.g. submaps.max_frames=20")
        try:
            value = yaml.safe_load(raw) if raw.strip() else None
        except yaml.YAMLError:
            value = raw
        _set_nested(overrides, key.strip(), value)
    _set_nested(overrides, "source.dataset", entry.source)
    if entry.path_argument and args.sequence is not None:
        path = Path(args.sequence).expanduser()
        if entry.source == "lidar":
            _set_nested(overrides, "source.root", str(path))
        else:  # an RGB-D folder: its parent is the root, its name the sequence
            resolved = path.resolve()
            _set_nested(overrides, "source.root", str(resolved.parent))
            _set_nested(overrides, "source.sequence", resolved.name)
    elif args.sequence is not None:
        _set_nested(overrides, "source.sequence", args.sequence)
    if args.root is not None:
        _set_nested(overrides, "source.root", str(args.root))
    if args.dataloader is not None:
        _set_nested(overrides, "source.lidar.dataloader", args.dataloader)
    if args.topic is not None:
        _set_nested(overrides, "source.lidar.topic", args.topic)
    if args.frames is not None:
        parse_frames(args.frames)
        _set_nested(overrides, "source.frames", args.frames)
    if args.odometry is not None:
        _set_nested(overrides, "odometry.method", args.odometry)
    if args.device is not None:
        _set_nested(overrides, "mapping.device", args.device)
    if args.no_viz:
        _set_nested(overrides, "viz.mode", "none")
    elif args.spawn:
        _set_nested(overrides, "viz.mode", "spawn")
    elif args.serve:
        _set_nested(overrides, "viz.mode", "serve")
    elif args.connect:
        _set_nested(overrides, "viz.mode", "connect")
        _set_nested(overrides, "viz.connect_url", args.connect)
    elif args.rrd is not None:
        _set_nested(overrides, "viz.mode", "rrd")
        _set_nested(overrides, "viz.rrd_path", str(args.rrd))
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
    cfg = load_run_config(path, cli_overrides(args, entry))
    if entry.path_argument and not Path(cfg.source.root).expanduser().exists():
        raise FileNotFoundError(f"{cfg.source.root} does not exist; pass the recording's path")
    if entry.needs_root:
        root = cfg.source.root
        if root is None:
            raise UsageError(f"{args.dataset} needs --root DIR, the folder holding the dataset")
        if not Path(root).expanduser().is_dir():
            raise FileNotFoundError(f"dataset root {root} does not exist; pass --root DIR")
    if cfg.source.frames is not None:
        parse_frames(cfg.source.frames)
    return entry, cfg


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
            return folder, False
        folder.mkdir(parents=True)
        return folder, True
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


def _scale_lidar_config(cfg: RunConfig, source) -> None:
    """``source.lidar.scale_from_first_scan``: fill unset scale-dependent fields (see
    slam/lidar_scale.py)."""
    from slam.lidar_scale import scale_config

    if source.sensor != "lidar" or not cfg.source.lidar.scale_from_first_scan:
        return
    try:
        scale_config(cfg, source[0].points)
    except ValueError as exc:
        raise DatasetError(f"{cfg.source.root}: {exc}; check the recording") from None


def _linger(seconds: float | None, announce) -> None:
    """Keep the process (and so the viewer servers) alive: ``seconds``, or until Ctrl-C."""
    if seconds is not None and seconds <= 0:
        return
    until = "Ctrl-C" if seconds is None else f"{seconds:g} s or Ctrl-C"
    announce(f"run finished; still serving the viewer until {until}")
    deadline = None if seconds is None else time.monotonic() + seconds
    try:
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.2 if deadline is None else min(0.2, max(0.0, deadline - time.monotonic())))
    except KeyboardInterrupt:
        announce("stopped serving")


def execute(
    entry: DatasetEntry,
    cfg: RunConfig,
    folder: Path,
    progress: bool,
    announce=None,
) -> dict[str, Any]:
    """Run the pipeline on the configured sequence and write the run folder; returns metrics.

    ``announce(line)`` receives what the user must see while the run goes on (the viewer URL of
    ``viz.mode: serve``, and the summary before serving on after the run).
    """

    from slam.builders import build_logger, build_map, build_odometry, build_source
    from slam.outputs import RunOutputs
    from slam.pipeline import SlamPipeline
    from slam.run_metrics import collect_metrics
    from slam.threads import apply_thread_budget

    def say(line: str) -> None:
        logger.info(line)
        if announce is not None:
            announce(line)

    threads = apply_thread_budget(cfg)
    if cfg.viz.mode == "none":  # nobody would see intermediate meshes
        cfg.viz.mesh_every_submaps = 10**9
        cfg.viz.mesh_after_remap = False
    outputs = RunOutputs(folder)
    outputs.write_config(cfg)
    start = time.perf_counter()
    source = build_source(cfg)
    _scale_lidar_config(cfg, source)
    outputs.write_config(cfg)
    sensor = source.sensor
    odometry = build_odometry(cfg, sensor)
    neural_map = build_map(cfg)
    viz = build_logger(cfg, sensor, outputs.recording_path)
    viewer_url = viz.viewer_url
    if viewer_url:
        say(f"viewer: {viewer_url}")
    pipeline = SlamPipeline(cfg, sensor, odometry, neural_map, viz)
    logger.info("%s: %d frames, sensor %s", source.name, len(source), sensor)

    def write_poses() -> None:
        outputs.write_poses(
            source.to_dataset_frame(pipeline.odometry_poses()),
            source.to_dataset_frame(pipeline.slam_poses()),
            pipeline.timestamps(),
        )

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(source), unit="frame", desc=source.name, dynamic_ncols=True)
    intrinsics = None
    loop_start = time.perf_counter()
    try:
        for frame in source.read_ahead():
            result = pipeline.process(frame)
            if intrinsics is None and frame.intrinsics is not None:
                intrinsics = frame.intrinsics
            if result.closed_submap_id is not None:
                write_poses()
                outputs.write_loops(pipeline.loop_candidates)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(
                    submaps=len(pipeline.submaps),
                    loops=len(pipeline.accepted_loops()),
                    refresh=False,
                )
        if bar is not None:
            bar.set_postfix_str("final optimisation and mesh")
        pipeline.finish()
    except BaseException:
        viz.close()  # keep what was recorded
        raise
    finally:
        if bar is not None:
            bar.close()
    pipeline_s = time.perf_counter() - loop_start
    write_poses()
    outputs.write_loops(pipeline.loop_candidates)
    mesh = neural_map.extract_mesh(threads=threads.mesh_threads)
    if cfg.output.write_mesh:
        outputs.write_mesh(mesh)
    if cfg.output.write_map:
        outputs.write_map(neural_map, list(pipeline.submaps.values()))
    wall_s = time.perf_counter() - start
    metrics = collect_metrics(
        pipeline,
        wall_s=wall_s,
        pipeline_s=pipeline_s,
        setup_s=loop_start - start,
        mesh=mesh,
        gt_mesh_path=source.gt_mesh_path,
        intrinsics=intrinsics,
        lidar_range_m=cfg.submaps.max_range_m if sensor == "lidar" else None,
        num_mesh_samples=cfg.output.mesh_samples,
        extra={"dataset": cfg.source.dataset, "sequence": cfg.source.sequence, "sensor": sensor},
    )
    outputs.write_metrics(metrics)
    viz.log_metrics(**_final_scalars(metrics))
    metrics["run_folder"] = str(folder)
    metrics["recording"] = (
        str(cfg.viz.rrd_path or outputs.recording_path)
        if cfg.viz.mode in ("rrd", "serve")
        else None
    )
    if viewer_url:
        for line in summary_lines(metrics):
            say(line)
        metrics["summary_announced"] = announce is not None
        _linger(cfg.viz.serve_linger_s, say)
    viz.close()
    return metrics


def _final_scalars(metrics: dict[str, Any]) -> dict[str, float]:
    out: dict[str, float] = {}
    trajectory = metrics.get("trajectory")
    if trajectory:
        out["final_ate_odometry_m"] = float(trajectory["odometry"]["ate_rmse_m"])
        out["final_ate_slam_m"] = float(trajectory["slam"]["ate_rmse_m"])
    mesh = metrics.get("mesh")
    if mesh and mesh.get("accuracy_m") is not None:
        out["final_mesh_accuracy_m"] = float(mesh["accuracy_m"])
    return out


def _length(value: float | None) -> str:
    if value is None or not np.isfinite(value):
        return "n/a"
    return f"{value * 100:.1f} cm" if value < 1.0 else f"{value:.2f} m"


_UNCULLED = {
    "frustum": "all ground truth in a camera's view, occluded surfaces too",
    "none": "the whole ground truth",
}


def summary_lines(metrics: dict[str, Any]) -> list[str]:
    """The short summary printed at the end of a run."""
    timing = metrics["timing"]
    loops = metrics["loops"]
    remap = metrics["remap"]
    rate = timing.get("frames_per_s")
    lines = [
        f"run folder: {metrics['run_folder']}",
        f"frames {metrics['num_frames']}: pipeline {rate or 0.0:.1f} frames/s "
        f"({timing.get('pipeline_s', timing['wall_s']):.1f} s); wall time {timing['wall_s']:.1f} s "
        "(with loading/generating data, final mesh and files)",
        f"submaps {metrics['num_submaps']}; "
        f"loops {loops['graph_inliers']} kept / {loops['verified']} verified / "
        f"{loops['candidates']} candidates",
        f"remapping: {remap['submaps_moved']} submap moves in {remap['events']} passes, "
        f"{remap['seconds_total']:.2f} s; map {metrics['map']['voxels']} voxels",
    ]
    trajectory = metrics.get("trajectory")
    if trajectory:
        lines.append(
            f"ATE odometry {_length(trajectory['odometry']['ate_rmse_m'])} -> "
            f"SLAM {_length(trajectory['slam']['ate_rmse_m'])}"
        )
    mesh = metrics.get("mesh")
    if mesh:
        culling = str(mesh.get("culling", ""))
        where = (
            "over observed surfaces"
            if culling.startswith("observed")
            else {"frustum": "over surfaces in view", "none": "over the whole ground truth"}.get(
                culling, f"culling {culling}"
            )
        )
        lines.append(
            f"mesh accuracy {_length(mesh['accuracy_m'])}, completion "
            f"{_length(mesh['completion_m'])}, completion ratio "
            f"{100 * mesh['completion_ratio']:.0f}% (< {_length(mesh['threshold_m'])}) {where}"
        )
        unculled = metrics.get("mesh_unculled")
        if unculled:
            lines.append(
                f"  unculled ({_UNCULLED.get(unculled.get('culling'), unculled.get('culling'))}): "
                f"completion {_length(unculled['completion_m'])}, ratio "
                f"{100 * unculled['completion_ratio']:.0f}%"
            )
    if metrics.get("recording"):
        lines.append(f"replay: rerun {metrics['recording']}")
    return lines


USER_ERRORS: tuple[type[BaseException], ...] = (
    UsageError,
    ConfigError,
    DatasetError,
    MapFileError,
    FileNotFoundError,
    NotADirectoryError,
    PermissionError,
    ValidationError,
)
"""Errors caused by the user's input: reported in one line, without a traceback."""


def _one_line(exc: BaseException) -> str:
    if isinstance(exc, ValidationError):
        return describe_validation_error(exc, "config")
    text = " ".join(str(exc).split())
    if isinstance(exc, FileNotFoundError) and exc.filename and str(exc.filename) not in text:
        text = f"{exc.filename}: {text}"
    return text or type(exc).__name__


def _discard_empty_run(folder: Path | None, created: bool) -> None:
    """Remove a run folder that this run created and that holds nothing but its log and config
    (the run never started). A folder the run did not create is never removed."""
    if folder is None or not created or not folder.is_dir():
        return
    if {p.name for p in folder.iterdir()} <= {"run.log", "config.yaml"}:
        logging.shutdown()
        for name in ("run.log", "config.yaml"):
            (folder / name).unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            folder.rmdir()


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    debug = "--debug" in (argv if argv is not None else sys.argv[1:])
    folder: Path | None = None
    created = False
    try:
        args = build_parser().parse_args(argv)
        entry, cfg = resolve_config(args)
        folder, created = run_folder(cfg, args)
        _setup_logging(folder / "run.log", args.verbose)
        metrics = execute(
            entry,
            cfg,
            folder,
            progress=not args.no_progress,
            announce=lambda line: print(line, file=sys.stderr, flush=True),
        )
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except USER_ERRORS as exc:
        if debug:
            raise
        _discard_empty_run(folder, created)
        status = 2 if isinstance(exc, UsageError) else 1
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return status
    if not metrics.get("summary_announced"):
        for line in summary_lines(metrics):
            print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
