"""The SLAM algorithm object: frames in, poses, loops and a remapped neural map out.

Per frame: odometry -> keyframer. When a submap closes: loop detection against older submaps ->
verified edges into the pose graph -> the closed submap is encoded into the neural map at its
optimised anchor pose -> submaps whose anchors moved are remapped. A frame's pose is always its
anchor's current estimate composed with the frame's odometry pose relative to that anchor, so the
whole trajectory follows every optimisation. The world frame is the first anchor (frame 0).

Everything is reported to a :class:`~slam.algorithm.viz.Logger`, unconditionally; what is recorded
depends
only on which logger the runner built. What only a recording needs (voxel centres, meshes, the
error so far) is handed over as a callable that the null logger never calls, and per-frame
logging is O(1): trajectories grow by one position, and the optimised one is recomputed only
when a loop moved the graph.

Map work (encode, fuse, remap) runs on a :class:`~slam.algorithm.map_worker.MapWorker` (a worker
thread when
``cfg.map_worker``), in submission order with pose snapshots taken here, so results do not
depend on timing.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from frontends.frame import Frame
from frontends.odometry.base import Odometry
from slam.algorithm.loops import LoopCandidate, LoopDetector
from slam.algorithm.map_worker import MapWorker
from slam.algorithm.memory import release_freed_memory
from slam.algorithm.pose_graph import PoseGraph
from slam.algorithm.remap import RemapEvent, Remapper
from slam.algorithm.submaps import Keyframer, SubmapRecord, transform_points
from slam.algorithm.viz import Logger
from slam.app.config import RunConfig

logger = logging.getLogger(__name__)

SCAN_LOG_MAX_POINTS = 30_000


def _clock() -> tuple[float, float]:
    """(wall, CPU time of the calling thread) in seconds."""
    return time.perf_counter(), time.thread_time()


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


@dataclass
class FrameResult:
    """What happened at one frame.

    Attributes:
        index: frame index.
        T_W_S_odometry: odometry pose.
        T_W_S: the SLAM estimate at this time (anchor estimate composed with the relative pose).
        submap_id: the submap the frame belongs to.
        closed_submap_id: the submap this frame closed, or None.
        loops: loop candidates examined at this frame.
        remap: the remapping pass run at this frame, or None (also None while the map worker
            has not run it yet: see :attr:`SlamPipeline.remapper` for every pass).
    """

    index: int
    T_W_S_odometry: np.ndarray
    T_W_S: np.ndarray
    submap_id: int
    closed_submap_id: int | None = None
    loops: list[LoopCandidate] = field(default_factory=list)
    remap: RemapEvent | None = None


def make_loop_detector(cfg: RunConfig, sensor: str) -> LoopDetector | None:
    """The loop detector for a sensor (None when loop closure is off)."""
    lc = cfg.loop_closure
    if not lc.enabled:
        return None
    method = sensor if lc.method == "auto" else lc.method
    if method == "lidar":
        from slam.algorithm.loop_lidar import LidarLoopDetector

        return LidarLoopDetector(lc)
    from slam.algorithm.loop_rgbd import RgbdLoopDetector

    return RgbdLoopDetector(lc)


class SlamPipeline:
    """Odometry, keyframing, neural mapping, loop closure, pose graph and remapping."""

    def __init__(
        self,
        cfg: RunConfig,
        sensor: str,
        odometry: Odometry,
        neural_map,
        viz: Logger,
        loop_detector: LoopDetector | None = None,
    ) -> None:
        self.cfg = cfg
        self.sensor = sensor
        self.odometry = odometry
        self.map = neural_map
        self.viz = viz
        self.keyframer = Keyframer(cfg.submaps)
        self.graph = PoseGraph(cfg.pose_graph)
        self.loop_detector = (
            loop_detector if loop_detector is not None else make_loop_detector(cfg, sensor)
        )
        self.remapper = Remapper(cfg.remap, neural_map)
        self.submaps: dict[int, object] = {}
        self.records: dict[int, SubmapRecord] = {}
        self.loop_candidates: list[LoopCandidate] = []
        self.timings_s: dict[str, list[float]] = defaultdict(list)
        # CPU seconds of the thread that ran each stage (the map worker's for mapping and
        # remap); odometry's own thread pool (KISS-ICP) is not counted
        self.stage_cpu_s: dict[str, float] = defaultdict(float)
        for stage in ("mapping", "remap", "map_logging", "map_worker_wait"):  # worker writes too
            self.timings_s[stage] = []
        self.worker = MapWorker(threaded=cfg.map_worker)
        self._tracks = {"odometry": _Track(), "optimized": _Track(), "gt": _Track()}
        self._num_accepted = 0
        self._last_remap_moved = False
        self._frame_submap: list[int] = []
        self._frames_of: dict[int, list[int]] = {}
        self._frame_T_A_S: list[np.ndarray] = []
        self._odometry_poses: list[np.ndarray] = []
        self._timestamps: list[float] = []
        self._gt: list[np.ndarray | None] = []
        self._T_W_Wgt: np.ndarray | None = None
        self._closed_count = 0
        self._finished = False

    # --- per frame ----------------------------------------------------------------------------

    def _timed(self, name: str, start: tuple[float, float]) -> tuple[float, float]:
        """Book the wall and thread-CPU time since ``start`` (a :func:`_clock` reading) to a
        stage; returns the new reading."""
        now = _clock()
        self.timings_s[name].append(now[0] - start[0])
        self.stage_cpu_s[name] += now[1] - start[1]
        return now

    def _map_frame(self, frame: Frame) -> Frame:
        """The frame whose points go into the map: the odometry's :meth:`Odometry.map_points`
        (e.g. KISS-ICP's deskewed scan) for frames without normals of their own."""
        if frame.normals is not None:
            return frame
        points = self.odometry.map_points(frame)
        if points is frame.points:
            return frame
        return Frame(
            index=frame.index,
            timestamp=frame.timestamp,
            points=np.asarray(points, dtype=np.float64),
            T_W_S_gt=frame.T_W_S_gt,
        )

    def process(self, frame: Frame) -> FrameResult:
        """Consume the next frame."""
        if self._finished:
            raise RuntimeError("process() after finish()")
        start = _clock()
        T_W_S_odometry = np.asarray(self.odometry.register(frame), dtype=np.float64)
        t = self._timed("odometry", start)

        closed, current, T_A_S = self.keyframer.add(self._map_frame(frame), T_W_S_odometry)
        if current.submap_id not in self.graph:
            covariance = self.odometry.take_covariance()
            self.graph.add_anchor(current.submap_id, current.T_W_A_odometry, covariance)
        self._timed("keyframing", t)

        self._frame_submap.append(current.submap_id)
        self._frames_of.setdefault(current.submap_id, []).append(len(self._frame_submap) - 1)
        self._frame_T_A_S.append(T_A_S)
        self._odometry_poses.append(T_W_S_odometry)
        self._timestamps.append(float(frame.timestamp))
        self._record_gt(frame)

        result = FrameResult(
            index=frame.index,
            T_W_S_odometry=T_W_S_odometry,
            T_W_S=self.graph.pose(current.submap_id) @ T_A_S,
            submap_id=current.submap_id,
        )
        if closed is not None:
            result.closed_submap_id = closed.submap_id
            result.loops, result.remap = self._on_submap_closed(closed, frame.index)
            result.T_W_S = self.graph.pose(current.submap_id) @ T_A_S
        self._track_frame(result, graph_moved=any(c.accepted for c in result.loops))
        self.timings_s["frame"].append(time.perf_counter() - start[0])
        self._log_frame(frame, result)
        return result

    def _record_gt(self, frame: Frame) -> None:
        gt = None if frame.T_W_S_gt is None else np.asarray(frame.T_W_S_gt, dtype=np.float64)
        if gt is not None and self._T_W_Wgt is None and not self._gt:
            self._T_W_Wgt = np.linalg.inv(gt)
        self._gt.append(gt)

    # --- submap boundaries --------------------------------------------------------------------

    def _on_submap_closed(
        self, record: SubmapRecord, frame_index: int
    ) -> tuple[list[LoopCandidate], RemapEvent | None]:
        self._closed_count += 1
        start = _clock()
        candidates: list[LoopCandidate] = []
        if self.loop_detector is not None:
            candidates = self.loop_detector.process(record, self.graph.poses())
        t = self._timed("loop_detection", start)
        added = False
        for candidate in candidates:
            if candidate.accepted and candidate.T_Ai_Aj is not None:
                edge = self.graph.add_loop(
                    candidate.reference_id,
                    candidate.query_id,
                    candidate.T_Ai_Aj,
                    covariance=candidate.covariance,
                )
                candidate.graph_inlier = edge.inlier
                added = True
                self._num_accepted += 1
        self.loop_candidates.extend(candidates)
        self._timed("pose_graph", t)

        # the keyframe's images were for loop detection; the map only needs the points
        record.keyframe = None
        self.records[record.submap_id] = record
        T_W_A = self.graph.pose(record.submap_id).copy()
        remap_poses = self.graph.poses() if added else None
        t = _clock()
        self.worker.submit(self._map_job, record, T_W_A, remap_poses, frame_index)
        self._timed("map_worker_wait", t)  # only when the worker is two submaps behind
        remap = None
        if added:
            if not self.worker.threaded:
                remap = self.remapper.events[-1] if self._last_remap_moved else None
            self._refresh_graph_inliers()
            self._log_loops()
        periodic = self._closed_count % self.cfg.viz.mesh_every_submaps == 0
        self.viz.log_map_from(lambda: self._map_snapshot(periodic, added))
        self.viz.log_metrics_from(self._errors_so_far)
        return candidates, remap

    def _map_job(
        self,
        record: SubmapRecord,
        T_W_A: np.ndarray,
        remap_poses: dict[int, np.ndarray] | None,
        frame_index: int,
    ) -> None:
        """Encode and fuse a closed submap, then remap if the graph moved (worker thread)."""
        start = _clock()
        self._encode(record, T_W_A)
        start = self._timed("mapping", start)
        self._last_remap_moved = False
        if remap_poses is not None:
            event = self.remapper.apply(self.submaps, remap_poses, frame_index)
            self._last_remap_moved = event.num_moved > 0
            self._timed("remap", start)
        release_freed_memory()

    def _encode(self, record: SubmapRecord, T_W_A: np.ndarray) -> None:
        if len(record.points_A) == 0:
            logger.warning("submap %d has no points; nothing to encode", record.submap_id)
            return
        logger.info(
            "submap %d: frames %d-%d, %d points",
            record.submap_id,
            record.frame_indices[0],
            record.frame_indices[-1],
            len(record.points_A),
        )
        submap = self.map.encode(record.submap_id, record.points_A, record.normals_A, T_W_A)
        self.map.fuse(submap)
        self.submaps[record.submap_id] = submap
        if not self.cfg.submaps.keep_points:
            # The map keeps the encoding; the raw points are not needed any more.
            record.points_A = np.zeros((0, 3))
            record.normals_A = np.zeros((0, 3))

    def _refresh_graph_inliers(self) -> None:
        """Copy the pose graph's current inlier decision onto the accepted candidates."""
        by_pair = {(e.i, e.j): e.inlier for e in self.graph.loops}
        for candidate in self.loop_candidates:
            if candidate.accepted:
                candidate.graph_inlier = by_pair.get(
                    (candidate.reference_id, candidate.query_id), candidate.graph_inlier
                )

    # --- end of the sequence ------------------------------------------------------------------

    def finish(self) -> RemapEvent | None:
        """Close the last submap, run the final batch optimisation and remap."""
        if self._finished:
            return None
        last_index = len(self._frame_submap) - 1
        closed = self.keyframer.finish()
        if closed is not None:
            self._on_submap_closed(closed, last_index)
        start = _clock()
        self.graph.optimize_batch()
        t = self._timed("pose_graph", start)
        self.worker.close()
        t = self._timed("map_worker_wait", t)
        remap = self.remapper.apply(self.submaps, self.graph.poses(), -1)
        release_freed_memory()
        self._timed("remap", t)
        self._refresh_graph_inliers()
        self._finished = True
        self._log_loops()
        self._tracks["optimized"].replace(self.slam_poses()[:, :3, 3])
        self._log_trajectories()
        self.viz.log_map_from(lambda: self._map_snapshot(True, False))
        self.viz.log_metrics_from(self._errors_so_far)
        return remap

    # --- results ------------------------------------------------------------------------------

    @property
    def num_frames(self) -> int:
        return len(self._frame_submap)

    def odometry_poses(self) -> np.ndarray:
        """(N, 4, 4) odometry poses of the frames processed so far."""
        return np.array(self._odometry_poses).reshape(-1, 4, 4)

    def slam_poses(self) -> np.ndarray:
        """(N, 4, 4) current SLAM estimates of the frames processed so far."""
        if not self._frame_submap:
            return np.zeros((0, 4, 4))
        anchors = self.graph.poses()
        T_W_A = np.array([anchors[s] for s in self._frame_submap])
        return T_W_A @ np.array(self._frame_T_A_S)

    def frame_anchors(self) -> tuple[np.ndarray, np.ndarray]:
        """Every frame's submap id ``(N,)`` and pose in its anchor frame ``T_A_S (N, 4, 4)``."""
        return np.array(self._frame_submap, dtype=np.int64), np.array(self._frame_T_A_S).reshape(
            -1, 4, 4
        )

    def submap_frames(self, submap_id: int) -> list[int]:
        """Indices (processing order) of the frames of a submap."""
        return self._frames_of.get(submap_id, [])

    def timestamps(self) -> np.ndarray:
        return np.array(self._timestamps)

    def gt_poses(self) -> np.ndarray | None:
        """(N, 4, 4) ground truth in its own world frame, or None when any frame lacks it."""
        if not self._gt or any(g is None for g in self._gt):
            return None
        return np.array(self._gt)

    def gt_poses_where_known(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(N, 4, 4) ground truth with NaN rows where a frame has none, and the (N,) mask of the
        frames that have one; None when no frame has ground truth."""
        if not any(g is not None for g in self._gt):
            return None
        mask = np.array([g is not None for g in self._gt])
        poses = np.full((len(self._gt), 4, 4), np.nan)
        poses[mask] = np.array([g for g in self._gt if g is not None])
        return poses, mask

    def drain(self) -> None:
        """Wait for the map worker (the map then reflects every submap closed so far)."""
        self.worker.drain()

    def accepted_loops(self) -> list[LoopCandidate]:
        return [c for c in self.loop_candidates if c.accepted]

    # --- logging ------------------------------------------------------------------------------

    def _track_frame(self, result: FrameResult, graph_moved: bool) -> None:
        self._tracks["odometry"].append(result.T_W_S_odometry[:3, 3])
        if graph_moved:  # a loop moved the anchors: every frame's estimate changed
            self._tracks["optimized"].replace(self.slam_poses()[:, :3, 3])
        else:
            self._tracks["optimized"].append(result.T_W_S[:3, 3])
        gt = self._gt[-1]
        if gt is not None and self._T_W_Wgt is not None:
            self._tracks["gt"].append((self._T_W_Wgt @ gt)[:3, 3])

    def _log_frame(self, frame: Frame, result: FrameResult) -> None:
        viz = self.viz
        viz.set_time(frame.index, float(frame.timestamp))
        if frame.index % self.cfg.viz.scan_every == 0:
            points = np.asarray(frame.points)
            colors = frame.colors
            step = max(1, len(points) // SCAN_LOG_MAX_POINTS)
            points = points[::step]
            colors = None if colors is None else np.asarray(colors)[::step]
            viz.log_scan(transform_points(result.T_W_S, points), colors)
            viz.log_sensor(result.T_W_S, frame.intrinsics, frame.rgb, frame.depth)
        self._log_trajectories()
        viz.log_metrics(
            frame_ms=1e3 * self.timings_s["frame"][-1],
            odometry_ms=1e3 * self.timings_s["odometry"][-1],
            submaps=float(self._closed_count),
            loops_accepted=float(self._num_accepted),
            loop_candidates=float(len(self.loop_candidates)),
        )

    def _log_trajectories(self) -> None:
        for name in ("odometry", "optimized"):
            self.viz.log_trajectory(name, self._tracks[name].view())
        gt = self._tracks["gt"].view()
        if len(gt) == self.num_frames and len(gt) > 0:
            self.viz.log_trajectory("gt", gt)

    def _log_loops(self) -> None:
        anchors = self.graph.poses()

        def segment(c: LoopCandidate) -> tuple[np.ndarray, np.ndarray] | None:
            if c.reference_id not in anchors or c.query_id not in anchors:
                return None
            return anchors[c.reference_id][:3, 3], anchors[c.query_id][:3, 3]

        accepted = [segment(c) for c in self.loop_candidates if c.accepted and c.graph_inlier]
        rejected = [segment(c) for c in self.loop_candidates if not (c.accepted and c.graph_inlier)]
        self.viz.log_loop_closures(
            [s for s in accepted if s is not None], [s for s in rejected if s is not None]
        )

    def _map_snapshot(self, periodic: bool, loop_added: bool):
        """What a recording shows of the map now (waits for the map worker); see
        :meth:`slam.algorithm.viz.Logger.log_map_from`."""
        self.worker.drain()
        start = _clock()
        centers, weights = self.map.voxel_centers()
        remapped = loop_added and self._last_remap_moved and self.cfg.viz.mesh_after_remap
        mesh = self.map.extract_mesh() if periodic or remapped else None
        self._timed("map_logging", start)
        return np.asarray(centers), np.asarray(weights, dtype=np.float64), mesh

    def _errors_so_far(self) -> dict[str, float]:
        """Map size and, with ground truth, the ATE of both trajectories so far (waits for the
        map worker)."""
        self.worker.drain()
        scalars = {"map_voxels": float(self.map.num_voxels)}
        gt = self.gt_poses()
        if gt is None or len(gt) < 3:
            return scalars
        from slam.evaluation.metrics.trajectory import ate_rmse

        scalars["ate_odometry_m"] = ate_rmse(self.odometry_poses(), gt)
        scalars["ate_slam_m"] = ate_rmse(self.slam_poses(), gt)
        return scalars
