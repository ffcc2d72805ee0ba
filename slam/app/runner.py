"""Run the pipeline on one configured sequence and write its run folder.

:func:`execute` builds the source, odometry, map and logger from a validated
:class:`~slam.assembly.config.RunConfig`, feeds every frame to
:class:`~slam.algorithm.pipeline.SlamPipeline`,
writes the outputs as the run goes (so a crash keeps what was written) and returns the metrics.
The command line around it is :mod:`slam.app.cli`.
"""

from __future__ import annotations

import copy
import logging
import re
import time
import uuid
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from frontends.errors import DatasetError
from frontends.odometry.base import Odometry
from slam.app.signals import Terminated
from slam.app.summary import summary_lines
from slam.assembly.config import RunConfig
from slam.assembly.datasets import DatasetEntry
from slam.run_folder.outputs import KittiRows
from slam.run_folder.write_behind import WriteBehind

logger = logging.getLogger("slam.run")


def _scale_lidar_config(cfg: RunConfig, source) -> None:
    """``source.lidar.scale_from_first_scan``: fill unset scale-dependent fields (see
    slam/lidar_scale.py)."""
    from slam.assembly.lidar_scale import scale_config

    if source.sensor != "lidar" or not cfg.source.lidar.scale_from_first_scan:
        return
    try:
        scale_config(cfg, source[0].points)
    except ValueError as exc:
        raise DatasetError(f"{cfg.source.root}: {exc}; check the recording") from None


def run_cpu_s(odometry: Odometry | None) -> float:
    """CPU seconds of this process and of its children that ended, plus those the odometry's
    running child process has used so far: the difference of two readings is the run's CPU
    time between them, the odometry's included, once that child ended."""
    import resource

    cpu_s = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        usage = resource.getrusage(who)
        cpu_s += usage.ru_utime + usage.ru_stime
    return cpu_s + (odometry.child_cpu_s() if odometry is not None else 0.0)


def _linger(seconds: float | None, announce) -> None:
    """Keep the process (and so the viewer servers) alive: ``seconds``, or until Ctrl-C."""
    if seconds is not None and seconds <= 0:
        return
    until = "Ctrl-C" if seconds is None else f"{seconds:g} s or Ctrl-C"
    deadline = None if seconds is None else time.monotonic() + seconds
    try:  # the announcement too: a Ctrl-C as soon as it is seen must not look like an interrupt
        announce(f"run finished; still serving the viewer until {until}")
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
    check_config=None,
    continued=None,
) -> dict[str, Any]:
    """Run the pipeline on the configured sequence and write the run folder; returns metrics.

    ``announce(line)`` receives what the user must see while the run goes on (the viewer URL of
    ``viz.mode: serve``, and the summary before serving on after the run). ``check_config(cfg)``
    may refuse the final config (after the first scan set its scale) by raising. ``continued``
    (a :class:`~slam.app.continue_map.ContinuedMap`, ``--map``) places the run in a stored map.

    ``run_status.json`` says whether the run finished (see :data:`RUN_STATUS_FILE`): it is
    ``running`` until the end (so a killed run stays ``running``), and ``interrupted``,
    ``terminated`` or ``failed`` when an exception ends it.
    """

    from slam.assembly.builders import build_source
    from slam.run_folder.outputs import RunOutputs

    outputs = RunOutputs(folder)
    outputs.write_config(cfg)
    source = build_source(cfg)
    _scale_lidar_config(cfg, source)
    outputs.write_config(cfg)
    if check_config is not None:
        check_config(cfg)
    state = _RunState(frames_total=len(source))
    outputs.write_status("running", 0, state.frames_total)
    try:
        return _run(entry, cfg, folder, progress, announce, outputs, source, state, continued)
    except BaseException as exc:
        _record_failure(outputs, state, exc)
        if state.viz is not None:
            try:  # keep what was recorded; never mask the error that ended the run
                state.viz.close()
            except Exception as close_exc:
                logger.warning("closing the recording failed: %s", close_exc)
        raise


@dataclass
class _RunState:
    """How far a run got (for ``run_status.json``)."""

    frames_total: int
    frames_done: int = 0
    viz: Any = None


def _record_failure(outputs, state: _RunState, exc: BaseException) -> None:
    """Write ``run_status.json`` for a run that an exception ended (best effort: the disk may
    be full)."""
    if isinstance(exc, Terminated):
        status, reason = "terminated", "SIGTERM"
    elif isinstance(exc, KeyboardInterrupt):
        status, reason = "interrupted", "Ctrl-C"
    else:
        status, reason = "failed", " ".join(f"{type(exc).__name__}: {exc}".split())[:200]
    try:
        outputs.write_status(status, state.frames_done, state.frames_total, reason)
    except OSError as write_exc:
        logger.warning("could not write the run status: %s", write_exc)


def _run(entry, cfg, folder, progress, announce, outputs, source, state: _RunState, continued):
    from slam.algorithm.pipeline import SlamPipeline
    from slam.app.recorder import build_logger, make_recorder
    from slam.assembly.builders import build_map, build_odometry
    from slam.assembly.threads import apply_thread_budget
    from slam.evaluation.run_metrics import collect_metrics

    def say(line: str) -> None:
        logger.info(line)
        if announce is not None:
            announce(line)

    threads = apply_thread_budget(cfg)
    if cfg.viz.mode == "none":  # nobody would see intermediate meshes
        cfg.viz.mesh_every_submaps = 10**9
        cfg.viz.mesh_after_remap = False
    start = time.perf_counter()
    sensor = source.sensor
    odometry = build_odometry(cfg, sensor)
    neural_map = build_map(cfg)
    viz = build_logger(cfg, sensor, outputs.recording_path)
    state.viz = viz
    viewer_url = viz.viewer_url
    if viewer_url:
        say(f"viewer: {viewer_url}")
    relocaliser = None
    localise_only = continued is not None and continued.localise_only
    if continued is not None:
        relocaliser = continued.relocaliser
        viz.log_stored_map(continued.mesh_path)
    pipeline = SlamPipeline(
        cfg.pipeline_config(),
        sensor,
        odometry,
        neural_map,
        relocaliser=relocaliser,
        encode=not localise_only,
    )
    stored_anchors = None if relocaliser is None else relocaliser.map_anchor_poses
    recorder = make_recorder(pipeline, viz, cfg.viz, stored_anchors)
    logger.info("%s: %d frames, sensor %s", source.name, len(source), sensor)

    kitti_rows: list[int] = []  # position in the sequence of each processed frame
    frame_indices: list[int] = []  # the dataset's index of each processed frame
    placed_at: list[int] = []  # the frame at which the run was placed in the stored map

    def poses() -> tuple:
        """The arguments of ``outputs.write_poses`` as of now (copies)."""
        return (
            source.to_dataset_frame(pipeline.frames.odometry_poses()),
            source.to_dataset_frame(pipeline.slam_poses()),
            pipeline.frames.timestamps(),
            KittiRows(np.asarray(kitti_rows), state.frames_done),
        )

    def write_progress() -> None:
        """The files a submap close rewrites, written behind the run from copies."""
        localisation = None
        if relocaliser is not None:
            localisation = _localisation_rows(pipeline, frame_indices)
        writes.submit(
            _write_progress,
            outputs,
            poses(),
            [copy.copy(candidate) for candidate in pipeline.loop_candidates],
            localisation,
            (state.frames_done, state.frames_total),
        )

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(source), unit="frame", desc=source.name, dynamic_ncols=True)
    intrinsics = None
    skipped: list[int] = []
    writes = WriteBehind()
    loop_start = time.perf_counter()
    cpu_start = run_cpu_s(odometry)
    try:
        for frame in source.read_ahead():
            state.frames_done += 1
            if len(frame.points) < cfg.source.min_points:
                skipped.append(frame.index)
                logger.warning(
                    "frame %d: %d points (< source.min_points %d); skipped",
                    frame.index,
                    len(frame.points),
                    cfg.source.min_points,
                )
                continue
            kitti_rows.append(state.frames_done - 1)
            frame_indices.append(frame.index)
            result = pipeline.process(frame)
            recorder.frame(frame, result)
            if result.relocalised is not None:
                placed_at.append(frame.index)
                line = _relocalised_line(frame.index, result.relocalised)
                logger.info("%s", line)
                if announce is not None:
                    (bar.write if bar is not None else announce)(line)
            if intrinsics is None and frame.intrinsics is not None:
                intrinsics = frame.intrinsics
            if result.closed_submap_id is not None:
                write_progress()
            if bar is not None:
                bar.update(1)
                bar.set_postfix(
                    submaps=len(pipeline.submaps),
                    loops=len(pipeline.accepted_loops()),
                    refresh=False,
                )
        if len(skipped) == state.frames_total:
            raise DatasetError(
                f"{cfg.source.root or source.name}: no usable frame, all {len(skipped)} have "
                "fewer than "
                f"{cfg.source.min_points} points (empty or truncated files?); check the recording"
            )
        if bar is not None:
            bar.set_postfix_str("final optimisation and mesh")
        pipeline.finish()
        # the rate ends with the final optimisation: the recording's exact final map is after it
        pipeline_s = time.perf_counter() - loop_start
        pipeline_cpu_s = run_cpu_s(None) - cpu_start  # the odometry's child was waited for
    except BaseException:  # Ctrl-C, SIGTERM, a failed job: stop the workers, skip their queue
        pipeline.abort()
        writes.abandon()  # before the failure's status is written
        raise
    finally:
        if bar is not None:
            bar.close()
    writes.close()  # before the final writes of the same files
    outputs.write_poses(*poses())
    outputs.write_loops(pipeline.loop_candidates)
    mesh = None if localise_only else neural_map.extract_mesh(threads=threads.mesh_threads)
    recorder.finish(mesh)  # the recording's exact final map: the same mesh, extracted once
    if mesh is not None and cfg.output.write_mesh:
        outputs.write_mesh(mesh)
    gt = pipeline.frames.gt_poses()
    if gt is not None and len(gt):
        outputs.write_ground_truth(
            source.to_dataset_frame(gt),
            pipeline.frames.timestamps(),
            KittiRows(np.asarray(kitti_rows), state.frames_done),
        )
    if cfg.output.write_map and not localise_only:
        from slam.algorithm.merge.session import session_from_pipeline

        setup = {
            "sensor": sensor,
            "dataset": cfg.source.dataset,
            "sequence": cfg.source.sequence,
            "frames": cfg.source.frames,
            "session_id": uuid.uuid4().hex,  # a merge refuses a session given twice
        }
        mirror = getattr(source, "dataset_mirror", None)
        session = session_from_pipeline(pipeline, setup, mirror)
        outputs.write_map(neural_map, list(pipeline.submaps.values()), session)
    wall_s = time.perf_counter() - start
    metrics = collect_metrics(
        pipeline.report(),
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
    metrics["timing"]["pipeline_cpu_s"] = pipeline_cpu_s
    metrics["input"] = {
        "frames_total": state.frames_total,
        "frames_processed": state.frames_total - len(skipped),
        "skipped_frames": skipped,
        "tracking_failures": odometry.num_failures,
        **source.data_choices(),
    }
    if localise_only:  # no submap was encoded: count the closed ones
        metrics["num_submaps"] = len(np.unique(pipeline.frames.anchors()[0]))
    if relocaliser is not None:
        metrics["relocalisation"] = _relocalisation_metrics(pipeline, relocaliser)
        metrics["localisation"] = _localisation(outputs, pipeline, frame_indices, placed_at)
    metrics["warnings"] = input_warnings(metrics, cfg.source.min_points, not localise_only)
    for warning in metrics["warnings"]:
        logger.warning("%s", warning)
    outputs.write_metrics(metrics)
    viz.log_metrics(**_final_scalars(metrics))
    metrics["run_folder"] = str(folder)
    metrics["recording"] = (
        str(cfg.viz.rrd_path or outputs.recording_path)
        if cfg.viz.mode in ("rrd", "serve")
        else None
    )
    outputs.write_status("finished", state.frames_done, state.frames_total)
    if viewer_url:
        viz.flush()  # the viewer shows the whole run while it is served on
        for line in summary_lines(metrics):
            say(line)
        metrics["summary_announced"] = announce is not None
        _linger(cfg.viz.serve_linger_s, say)
    viz.close()
    return metrics


def _relocalised_line(frame_index: int, found) -> str:
    scores = found.scores
    return (
        f"relocalised in the map at frame {frame_index}: submap {found.submap_id} on the map's "
        f"submap {found.map_submap_id} (inlier fraction {scores['inlier_fraction']:.2f}, "
        f"residual {100 * scores['residual_sigma_m']:.1f} cm; {found.attempts} submaps tried); "
        "poses and map from here on are in the map's frame"
    )


def _relocalisation_metrics(pipeline, relocaliser) -> dict[str, Any]:
    """``metrics.json``'s ``relocalisation``: where and how the run was placed in the map."""
    found = pipeline.relocalisation
    out: dict[str, Any] = {
        "relocalised": found is not None,
        "submaps_tried": relocaliser.attempts,
        "seconds": relocaliser.seconds,
        "map_decode_seconds": relocaliser.decode_seconds,
    }
    if found is not None:
        out.update(
            submap=found.submap_id,
            submap_frames=list(found.frames),
            map_submap=found.map_submap_id,
            T_M_W=found.T_M_W.tolist(),
            scores={k: float(v) for k, v in found.scores.items()},
        )
    return out


def _localisation_rows(pipeline, frame_indices: list[int]) -> tuple[list, list, list, list]:
    """The columns of ``localisation.csv`` (:func:`slam.run_folder.localisation.localisation_csv`)
    as the main thread knows them now, as copies: every processed frame's status."""
    from slam.run_folder.localisation import frame_statuses

    frame_submaps = pipeline.frames.anchors()[0].tolist()
    statuses = frame_statuses(frame_submaps, pipeline.map_anchored)
    return list(frame_indices), pipeline.frames.timestamps().tolist(), frame_submaps, statuses


def _write_progress(
    outputs, poses: tuple, candidates: list, localisation: tuple | None, frames: tuple[int, int]
) -> None:
    """The files a submap close rewrites (on the write-behind thread, from copies): the
    trajectories, ``loops.csv``, ``localisation.csv`` (in a stored map) and the status."""
    from slam.run_folder.localisation import localisation_csv

    outputs.write_poses(*poses)
    outputs.write_loops(candidates)
    if localisation is not None:
        outputs.write_localisation(localisation_csv(*localisation))
    outputs.write_status("running", *frames)


def _localisation(outputs, pipeline, frame_indices: list[int], placed_at: list[int]) -> dict:
    """Write the final ``localisation.csv`` and return ``metrics.json``'s ``localisation``
    (after ``pipeline.finish()``)."""
    from slam.run_folder.localisation import localisation_csv, localisation_summary

    rows = _localisation_rows(pipeline, frame_indices)
    outputs.write_localisation(localisation_csv(*rows))
    frame_submaps, statuses = rows[2], rows[3]
    found, localisation = pipeline.relocalisation, pipeline.localisation
    summary = localisation_summary(
        frame_indices,
        frame_submaps,
        statuses,
        None if found is None else found.submap_id,
        placed_at[0] if placed_at else None,
    )
    constraints = [] if localisation is None else localisation.constraints
    summary["submaps_registered"] = sum(c.accepted for c in constraints)
    summary["submaps_not_registered"] = dict(
        Counter(re.split(r"[\d:(]", c.reason)[0].strip() for c in constraints if not c.accepted)
    )
    if localisation is not None:
        summary["registration_seconds"] = localisation.registration_seconds
    return summary


def input_warnings(metrics: dict[str, Any], min_points: int, maps: bool = True) -> list[str]:
    """What makes a finished run's result doubtful: skipped frames, tracking failures, an
    empty map when the run ``maps`` (each also in ``metrics.json``)."""
    warnings = []
    info = metrics["input"]
    skipped = info["skipped_frames"]
    if skipped:
        shown = ", ".join(str(i) for i in skipped[:10]) + (", ..." if len(skipped) > 10 else "")
        warnings.append(
            f"{len(skipped)} of {info['frames_total']} frames skipped (fewer than {min_points} "
            f"points): {shown}"
        )
    if info["tracking_failures"]:
        warnings.append(
            f"odometry failed on {info['tracking_failures']} frames (pose extrapolated)"
        )
    if maps and not metrics.get("map", {}).get("voxels"):
        warnings.append("the map is empty: no depth or points were fused")
    return warnings


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
