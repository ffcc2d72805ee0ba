"""``python -m slam.merge RUN_DIR RUN_DIR [RUN_DIR ...] --out DIR``: merge runs into one map.

Reads only each run folder's ``map.npz`` (latents and session section), and, for evaluation and
the recording, ``poses_gt.kitti.txt`` and ``mesh.ply`` where present; never a scan. A map file
may come from elsewhere: its sizes, header and session are checked before use
(:func:`mapping.map_io.read_map_file`, :mod:`slam.algorithm.merge.session_checks`), and it is
decoded with this command's prior (``--weights``, default the shipped one) and device, never
with a file or device its header names. ``DIR`` is claimed and written through a hidden sibling
folder renamed at the end (:func:`common.atomic_folder.atomic_folder`): a merge that fails
(incompatible maps, a run that shares no place with the others, a full disk, Ctrl-C or SIGTERM)
leaves nothing and exits non-zero with one line on stderr (130 and 143 for the signals), and a
second merge into the same ``DIR`` is refused while the first runs.

``DIR`` receives what a run writes: ``poses_slam.{kitti,tum}.txt`` (every session's frames in the
order the runs were given, in the first run's frame), ``sessions.csv``, ``loops.csv``,
``map.npz`` (itself a session: a merged run can be merged again), ``mesh.ply``, ``metrics.json``
and ``recording.rrd``.
"""

from __future__ import annotations

import argparse
import logging
import resource
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from common.atomic_folder import FolderBusyError, atomic_folder
from frontends.errors import DatasetError
from mapping.config import MapConfig
from mapping.errors import MapFileError, WeightsFileError
from mapping.map_io import load_map, load_session, read_map_file
from slam.app.signals import Terminated, handle_sigterm, restore_sigterm
from slam.assembly.config import OneLineParser, UsageError

logger = logging.getLogger("slam.merge")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="python -m slam.merge",
        description="Merge separate runs into one loop-closed neural map (no raw data needed).",
    )
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (the first sets the frame)")
    parser.add_argument("--out", type=Path, required=True, help="new or empty output folder")
    parser.add_argument(
        "--weights",
        type=Path,
        help="prior weights the maps were made with (default: the shipped prior)",
    )
    parser.add_argument("--no-viz", action="store_true", help="write no Rerun recording")
    parser.add_argument("-v", "--verbose", action="store_true", help="log INFO to stderr")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    return parser


def load_run(folder: Path, settings: MapConfig | None = None):
    """``(SessionInput, NeuralMap)`` of a run folder, decoded with ``settings``' prior and device
    (the command's own; default: the shipped prior); a bad folder is a one-line error."""
    from slam.algorithm.merge.merge import SessionInput
    from slam.algorithm.merge.session import SESSION_ARRAYS, SessionRecord

    path = folder / "map.npz"
    if not folder.is_dir():
        raise DatasetError(f"{folder}: run folder not found; give folders written by slam.run")
    data = read_map_file(path, settings, session=SESSION_ARRAYS)
    _, session_header, arrays = load_session(path, data=data)
    try:
        session = SessionRecord.from_arrays(session_header, arrays)
    except (KeyError, ValueError, TypeError, IndexError) as exc:
        raise MapFileError(
            f"{path}: session section is inconsistent ({exc}); re-run slam.run"
        ) from exc
    neural_map, submaps = load_map(path, settings=settings, data=data)
    return SessionInput(str(folder), session, submaps), neural_map


def _ground_truth(folder: Path, rows: int) -> np.ndarray | None:
    from slam.run_folder.trajectory_io import read_kitti

    path = folder / "poses_gt.kitti.txt"
    if not path.is_file():
        return None
    poses = read_kitti(path)
    return poses if len(poses) == rows else None


def _metrics(result, inputs, folders: list[Path], seconds: float) -> dict[str, Any]:
    from slam.evaluation.metrics.trajectory import ate_rmse

    sessions, est_all, gt_all = [], [], []
    for k, (item, folder) in enumerate(zip(inputs, folders, strict=True)):
        poses = item.session.to_dataset_frame(result.frame_poses[k])
        entry: dict[str, Any] = {"session": k, "run_folder": str(folder), "frames": len(poses)}
        gt = _ground_truth(folder, len(poses))
        if gt is not None and len(poses) >= 3:
            entry["ate_rmse_m"] = ate_rmse(poses, gt)
            entry["ate_rmse_m_run"] = ate_rmse(
                item.session.to_dataset_frame(item.session.frame_poses()), gt
            )
            est_all.append(poses)
            gt_all.append(gt)
        sessions.append(entry)
    accepted = [c for c in result.loops if c.accepted]
    metrics: dict[str, Any] = {
        "sessions": sessions,
        "inter_session_candidates": len(result.loops),
        "inter_session_loops_verified": len(accepted),
        "inter_session_loops_kept": sum(bool(c.graph_inlier) for c in accepted),
        "intra_session_loops": len(result.intra_loops),
        "submaps": len(result.submaps),
        "map_voxels": result.neural_map.num_voxels,
        "seconds": {**result.seconds, "total": seconds},
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    if len(est_all) == len(inputs):
        metrics["combined_ate_rmse_m"] = ate_rmse(np.concatenate(est_all), np.concatenate(gt_all))
    return metrics


def _session_rows(inputs, folders: list[Path]) -> tuple[list[str], list[int]]:
    """Run folder and rows of every session; a merged run lists the runs it joined."""
    names, rows = [], []
    for item, folder in zip(inputs, folders, strict=True):
        parts = item.session.parts or [{"name": str(folder), "rows": len(item.session.timestamps)}]
        names += [str(part["name"]) for part in parts]
        rows += [int(part["rows"]) for part in parts]
    return names, rows


def merge(args: argparse.Namespace) -> dict[str, Any]:
    """Load, merge and write; returns the metrics."""
    start = time.perf_counter()
    settings = MapConfig(weights_path=None if args.weights is None else str(args.weights))
    with atomic_folder(args.out) as partial:  # claimed and proven writable before any work
        loaded = [load_run(folder, settings) for folder in args.runs]
        return merge_runs(loaded, args.runs, partial, not args.no_viz, start)


def merge_runs(
    loaded: list, folders: list[Path], out: Path, viz: bool, start: float
) -> dict[str, Any]:
    """Merge loaded runs (:func:`load_run` of each of ``folders``) and write the merged run
    folder ``out``; returns the metrics. Nothing is written when the merge fails."""
    import trimesh

    from common.atomic_io import write_text_atomic
    from slam.algorithm.merge.merge import merge_sessions
    from slam.app.merge_outputs import merge_loops_csv, sessions_csv, write_recording
    from slam.assembly.threads import apply_plan, plan_thread_budget
    from slam.run_folder.outputs import RunOutputs

    # torch on one thread fewer than the cores, as in a run: a pool as wide as the machine
    # spins against anything else running (a merge of the room took minutes, not seconds)
    threads = apply_plan(plan_thread_budget(0, map_worker=True))
    inputs = [item for item, _ in loaded]
    maps = [m for _, m in loaded]
    result = merge_sessions(inputs, maps)
    mesh_start = time.perf_counter()
    mesh = result.neural_map.extract_mesh(threads=threads.mesh_threads)
    result.seconds["mesh"] = time.perf_counter() - mesh_start
    seconds = time.perf_counter() - start
    metrics = _metrics(result, inputs, folders, seconds)

    outputs = RunOutputs(out)
    first = inputs[0].session
    poses = np.concatenate([first.to_dataset_frame(p) for p in result.frame_poses])
    timestamps = np.concatenate([item.session.timestamps for item in inputs])
    outputs.write_poses(poses, poses, timestamps)
    for name in ("poses_odometry.kitti.txt", "poses_odometry.tum.txt"):
        outputs.path(name).unlink(missing_ok=True)  # a merge has no odometry of its own
    truth = [
        _ground_truth(folder, len(p)) for folder, p in zip(folders, result.frame_poses, strict=True)
    ]
    if all(gt is not None for gt in truth):  # kept, so that a merged run can be evaluated
        outputs.write_ground_truth(np.concatenate(truth), timestamps)
    names, rows = _session_rows(inputs, folders)
    write_text_atomic(outputs.path("sessions.csv"), sessions_csv(names, rows))
    write_text_atomic(outputs.path("loops.csv"), merge_loops_csv(result))
    outputs.write_map(result.neural_map, result.submaps, result.session)
    outputs.write_mesh(mesh)
    outputs.write_metrics(metrics)
    frames = len(timestamps)
    outputs.write_status("finished", frames, frames)
    if viz:
        before = []
        for folder in folders:
            path = folder / "mesh.ply"
            before.append(trimesh.load(path, force="mesh") if path.is_file() else None)
        labels = [str(folder) for folder in folders]
        write_recording(outputs.recording_path, result, labels, before, mesh)
    return metrics


def _os_error_line(exc: OSError) -> str:
    where = f"{exc.filename}: " if exc.filename else ""
    return f"{where}{exc.strerror or exc}; pass --out on a writable disk with free space"


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    previous_sigterm = handle_sigterm()
    try:
        return _main(argv)
    finally:
        restore_sigterm(previous_sigterm)


def _main(argv: list[str] | None) -> int:
    from slam.algorithm.merge.merge import MergeError

    debug = "--debug" in (argv if argv is not None else sys.argv[1:])
    try:
        args = build_parser().parse_args(argv)
        logging.basicConfig(
            level=logging.INFO if args.verbose else logging.WARNING,
            format="%(levelname)s %(name)s: %(message)s",
        )
        metrics = merge(args)
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, Terminated)
        cause = "terminated (SIGTERM)" if terminated else "interrupted"
        print(f"error: {cause}; nothing written", file=sys.stderr)
        return 128 + signal.SIGTERM if terminated else 130
    except (
        UsageError, MergeError, MapFileError, WeightsFileError, DatasetError, FolderBusyError,
        OSError,
    ) as exc:  # fmt: skip
        if debug:
            raise
        line = _os_error_line(exc) if isinstance(exc, OSError) else str(exc)
        print(f"error: {' '.join(line.split())}", file=sys.stderr)
        return 2 if isinstance(exc, UsageError | FolderBusyError) else 1
    loops = metrics["inter_session_loops_kept"]
    line = f"merged {len(metrics['sessions'])} runs: {loops} inter-session loops kept"
    if "combined_ate_rmse_m" in metrics:
        line += f", combined ATE {100 * metrics['combined_ate_rmse_m']:.2f} cm"
    print(f"{line}; wrote {args.out}")
    return 0
