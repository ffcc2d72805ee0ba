"""What a run shows in the viewer: the pipeline's results handed to a
:class:`~slam.algorithm.viz.Logger`.

The runner calls :meth:`RunRecorder.frame` with every frame and its
:class:`~slam.algorithm.pipeline.FrameResult` and :meth:`RunRecorder.finish` after the pipeline's
:meth:`~slam.algorithm.pipeline.SlamPipeline.finish`. Per frame the cost is O(1): trajectories
grow by one position, and the optimised one is recomputed only when a loop moved the graph. What
only a recording needs (voxel centres, meshes, the error so far) is handed to the logger as a
callable that the null logger never calls, and :func:`make_recorder` gives a recorder that does
nothing at all for the null logger.

The recorder never waits for the pipeline's workers during the run: at each closed submap it logs
the map the map worker published after its latest finished job
(:meth:`~slam.algorithm.pipeline.SlamPipeline.latest_map`, meshes extracted on that worker), and
the trajectories and loops as the main thread knows them. After the run it logs the exact final
map, trajectories and errors.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from common.geometry import transform_points
from frontends.frame import Frame
from slam.algorithm.executor import MapSnapshot, MapSnapshotRequest
from slam.algorithm.frame_result import FrameResult
from slam.algorithm.pipeline import SlamPipeline
from slam.algorithm.viz import Logger, NullLogger
from slam.assembly.config import RunConfig, VizConfig

SCAN_LOG_MAX_POINTS = 30_000


class _Track:
    """A growing (N, 3) array with amortised O(1) append; :meth:`view` shares memory."""

    def __init__(self) -> None:
        self._data = np.zeros((256, 3))
        self._size = 0

    def append(self, position: np.ndarray) -> None:
        if self._size == len(self._data):
            self._data = np.concatenate([self._data, np.zeros_like(self._data)])
        self._data[self._size] = position
        self._size += 1

    def replace(self, positions: np.ndarray) -> None:
        self._data = np.array(positions, dtype=np.float64).reshape(-1, 3)
        self._size = len(self._data)

    def view(self) -> np.ndarray:
        return self._data[: self._size]


class Recorder:
    """Does nothing: the recorder of a run whose logger records nothing."""

    def frame(self, frame: Frame, result: FrameResult) -> None:
        """Report one processed frame."""

    def finish(self, mesh: trimesh.Trimesh | None) -> None:
        """Report the end of the run (after the pipeline's final optimisation), with the final
        mesh the run extracted for its outputs (None when it keeps no map)."""


class RunRecorder(Recorder):
    """Trajectories, scans, loop edges, map snapshots and live metrics of a run; in a stored
    map also which stored submaps hold it and, per frame, ``map_anchored``: 1 when the latest
    submap whose registration the main thread knows is map-anchored (the frame's pose is carried
    from it by the odometry), else 0."""

    def __init__(
        self,
        pipeline: SlamPipeline,
        viz: Logger,
        cfg: VizConfig,
        map_anchor_poses: dict[int, np.ndarray] | None = None,
    ) -> None:
        self.pipeline = pipeline
        self.viz = viz
        self.cfg = cfg
        self._tracks = {"odometry": _Track(), "optimized": _Track(), "gt": _Track()}
        self._T_W_Wgt: np.ndarray | None = None
        self._T_W_O = np.eye(4)  # the odometry's frame in the shown world (moves at relocalisation)
        self._num_frames = 0
        self._map_job = 0  # the latest map job whose snapshot was logged
        self._mesh_job = 0  # the latest map job whose mesh was logged
        self._map_anchor_poses = map_anchor_poses  # the stored submaps' (a run in a stored map)
        self._closed: int | None = None  # the latest submap closed
        self._registered: int | None = None  # the latest closed submap whose result is known
        pipeline.request_map_snapshots(
            MapSnapshotRequest(cfg.mesh_every_submaps, cfg.mesh_after_remap, cfg.mesh_time_share)
        )

    def frame(self, frame: Frame, result: FrameResult) -> None:
        viz = self.viz
        viz.set_time(frame.index, float(frame.timestamp))
        if result.closed_submap_id is not None:
            if result.loop_added:
                self._log_loops()
            snapshot = self.pipeline.latest_map()
            if snapshot is not None and snapshot.job > self._map_job:
                viz.log_map_from(lambda: self._published_map(snapshot))
            viz.log_metrics_from(self._errors_so_far)
            self._registered, self._closed = self._closed, result.closed_submap_id
            if self._map_anchor_poses is not None:
                self._log_map_anchoring()
        self._track(frame, result)
        if frame.index % self.cfg.scan_every == 0:
            points = np.asarray(frame.points)
            colors = frame.colors
            step = max(1, len(points) // SCAN_LOG_MAX_POINTS)
            points = points[::step]
            colors = None if colors is None else np.asarray(colors)[::step]
            viz.log_scan(points, colors, T_W_S=result.T_W_S)
            viz.log_sensor(result.T_W_S, frame.intrinsics, frame.rgb, frame.depth)
        self._log_trajectories()
        viz.log_metrics(
            frame_ms=1e3 * result.frame_s,
            odometry_ms=1e3 * result.odometry_s,
            submaps=float(self.pipeline.num_closed_submaps),
            loops_accepted=float(self.pipeline.num_accepted_loops),
            loop_candidates=float(len(self.pipeline.loop_candidates)),
        )
        if self._map_anchor_poses is not None:
            viz.log_metrics(map_anchored=float(self._registered in self.pipeline.map_anchored))

    def finish(self, mesh: trimesh.Trimesh | None) -> None:
        self._log_loops()
        if self._map_anchor_poses is not None:
            self._log_map_anchoring()
        self._tracks["optimized"].replace(self.pipeline.slam_poses()[:, :3, 3])
        self._log_trajectories()
        self.viz.log_map_from(lambda: (*self.pipeline.map_voxels(), mesh))
        self.viz.log_metrics_from(self._errors_so_far)
        # a logger on its own thread is done with the mesh before the run writes and scores it
        self.viz.flush()

    def _track(self, frame: Frame, result: FrameResult) -> None:
        if result.relocalised is not None:
            self._move_to_map(result.relocalised.T_M_W)
        self._tracks["odometry"].append((self._T_W_O @ result.T_W_S_odometry)[:3, 3])
        if result.loop_added:  # a loop moved the anchors: every frame's estimate changed
            self._tracks["optimized"].replace(self.pipeline.slam_poses()[:, :3, 3])
        else:
            self._tracks["optimized"].append(result.T_W_S[:3, 3])
        if frame.T_W_S_gt is not None:
            gt = np.asarray(frame.T_W_S_gt, dtype=np.float64)
            if self._num_frames == 0:  # the ground truth's world, moved onto W = the first frame
                self._T_W_Wgt = np.linalg.inv(gt)
            if self._T_W_Wgt is not None:
                self._tracks["gt"].append((self._T_W_Wgt @ gt)[:3, 3])
        self._num_frames += 1

    def _move_to_map(self, T_M_W: np.ndarray) -> None:
        """The run was placed in a stored map: its odometry and ground-truth tracks follow the
        optimised one into the map's frame."""
        self._T_W_O = T_M_W @ self._T_W_O
        self._tracks["odometry"].replace(transform_points(T_M_W, self._tracks["odometry"].view()))
        self._tracks["gt"].replace(transform_points(T_M_W, self._tracks["gt"].view()))
        if self._T_W_Wgt is not None:
            self._T_W_Wgt = T_M_W @ self._T_W_Wgt

    def _log_trajectories(self) -> None:
        for name in ("odometry", "optimized"):
            self.viz.log_trajectory(name, self._tracks[name].view())
        gt = self._tracks["gt"].view()
        if len(gt) == self._num_frames and len(gt) > 0:
            self.viz.log_trajectory("gt", gt)

    def _log_loops(self) -> None:
        anchors = self.pipeline.anchor_poses()
        accepted, rejected = [], []
        for c in self.pipeline.loop_candidates:
            if c.reference_id not in anchors or c.query_id not in anchors:
                continue
            segment = anchors[c.reference_id][:3, 3], anchors[c.query_id][:3, 3]
            (accepted if c.accepted and c.graph_inlier else rejected).append(segment)
        self.viz.log_loop_closures(accepted, rejected)

    def _log_map_anchoring(self) -> None:
        """A segment from each map-anchored live submap's anchor to each stored submap it was
        registered to (the graph is in the map's frame from the placement on)."""
        assert self._map_anchor_poses is not None
        anchors = self.pipeline.anchor_poses()
        segments = [
            (anchors[live][:3, 3], self._map_anchor_poses[stored][:3, 3])
            for live, stored_ids in self.pipeline.map_anchored.items()
            if live in anchors
            for stored in stored_ids
        ]
        self.viz.log_map_anchoring(segments)

    def _published_map(self, snapshot: MapSnapshot):
        """The map the map worker published: voxel centres, weights and its mesh when that is
        newer than the last one logged (a mesh every ``mesh_every_submaps`` closed submaps and
        after every remap that moved a submap, when ``mesh_after_remap``, within
        ``mesh_time_share``)."""
        self._map_job = snapshot.job
        mesh = None
        if snapshot.mesh is not None and snapshot.mesh_job > self._mesh_job:
            mesh, self._mesh_job = snapshot.mesh, snapshot.mesh_job
        return snapshot.voxel_centers, snapshot.voxel_weights, mesh

    def _errors_so_far(self) -> dict[str, float]:
        """Map size and, with ground truth, the ATE of both trajectories so far: as far as the
        main thread knows them during the run (never waiting for the workers), exact after
        it."""
        from slam.evaluation.metrics.trajectory import ate_rmse

        scalars = {}
        snapshot = self.pipeline.latest_map()
        if self.pipeline.finished:
            scalars["map_voxels"] = float(self.pipeline.map.num_voxels)
        elif snapshot is not None:
            scalars["map_voxels"] = float(len(snapshot.voxel_centers))
        gt = self.pipeline.frames.gt_poses()
        if gt is None or len(gt) < 3:
            return scalars
        scalars["ate_odometry_m"] = ate_rmse(self.pipeline.frames.odometry_poses(), gt)
        scalars["ate_slam_m"] = ate_rmse(self.pipeline.slam_poses(), gt)
        return scalars


def make_recorder(
    pipeline: SlamPipeline,
    viz: Logger,
    cfg: VizConfig,
    map_anchor_poses: dict[int, np.ndarray] | None = None,
) -> Recorder:
    """A :class:`RunRecorder`, or a recorder that does nothing for the :class:`NullLogger`;
    ``map_anchor_poses``: the stored submaps' anchors of a run in a stored map (it then shows
    which of them hold the run, and each frame's status)."""
    if isinstance(viz, NullLogger):
        return Recorder()
    return RunRecorder(pipeline, viz, cfg, map_anchor_poses)


def build_logger(cfg: RunConfig, sensor: str, default_rrd: Path) -> Logger:
    """Rerun logger for the configured sink, or :class:`NullLogger`."""
    viz = cfg.viz
    if viz.mode == "none":
        return NullLogger()
    from slam.app.rerun_logger import RerunLogger
    from slam.app.threaded_logger import ThreadedLogger

    options: dict[str, Any] = {
        "voxel_size_m": cfg.mapping.voxel_size_m,
        "up_axis": "+z" if sensor == "lidar" else "-y",
        "flush_timeout_s": viz.flush_timeout_s,
    }
    if viz.mode == "rrd":
        options["rrd_path"] = viz.rrd_path or default_rrd
    elif viz.mode == "spawn":
        options["spawn"] = True
    elif viz.mode == "serve":
        options.update(
            rrd_path=viz.rrd_path or default_rrd,
            serve_port=viz.serve_grpc_port,
            web_port=viz.serve_web_port,
            serve_bind_ip=viz.serve_bind_ip,
        )
    else:
        if not viz.connect_url:
            raise ValueError("viz.mode 'connect' needs viz.connect_url")
        options["connect_url"] = viz.connect_url
    return ThreadedLogger(RerunLogger(**options))
