"""The SLAM algorithm object: frames in, poses, loops and a remapped neural map out.

Per frame: odometry -> keyframer. When a submap closes: loop detection against older submaps ->
verified edges into the pose graph -> the closed submap is encoded into the neural map at its
optimised anchor pose -> submaps whose anchors moved are remapped. A frame's pose is always its
anchor's current estimate composed with the frame's odometry pose relative to that anchor, so the
whole trajectory follows every optimisation. The world frame is the first anchor (frame 0).

The pipeline neither logs nor scores: each :meth:`SlamPipeline.process` returns a
:class:`FrameResult` (what happened at that frame), :meth:`SlamPipeline.map_voxels` gives what a
viewer shows of the map, and :meth:`SlamPipeline.report` what metrics need at the end.

Only the odometry and the keyframing *decision* (poses only) run in :meth:`SlamPipeline.process`'s
thread. The rest runs on the two workers of an :class:`~slam.algorithm.executor.Executor`
(threads when ``cfg.map_worker``), each in submission order: the *submap worker* absorbs every
frame's points into its submap (:class:`~slam.algorithm.submaps.SubmapPoints`, which only it
touches), closes submaps (normals, loop cloud), detects and verifies loops and owns the pose
graph; the *map worker* encodes, fuses and remaps. The main thread sees the graph through the
executor's :class:`~slam.algorithm.graph_view.GraphView`, updated at fixed frames, so results do
not depend on timing, and the map through the snapshot the map worker publishes after each job.

With a :class:`~slam.algorithm.merge.relocalise.Relocaliser` (``slam.run --map``), each closed
submap is also tried against a stored map until one verifies; the graph is then re-expressed in the
map's frame, every later result is in that frame, and each later closed submap is registered to
the stored map and anchored in it (:mod:`slam.algorithm.localisation`). Without ``encode`` (a
localisation-only run) no submap is encoded: the run keeps poses only.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from common.memory import keep_large_allocations_apart, release_freed_memory
from frontends.frame import Frame
from frontends.odometry.base import Odometry, OdometryResult
from slam.algorithm.config import PipelineConfig
from slam.algorithm.executor import (
    Executor,
    MapSnapshot,
    MapSnapshotRequest,
    SubmapJobResult,
    clock,
)
from slam.algorithm.frame_result import FrameResult
from slam.algorithm.frame_track import FrameTrack
from slam.algorithm.graph.gravity import measure_up
from slam.algorithm.graph.pose_graph import PoseGraph
from slam.algorithm.graph_view import GraphSnapshot
from slam.algorithm.localisation import MapLocalisation
from slam.algorithm.loops.base import LoopCandidate, LoopDetector
from slam.algorithm.loops.registry import make_loop_detector
from slam.algorithm.map_worker import job_result
from slam.algorithm.remap import RemapEvent, Remapper
from slam.algorithm.report import PipelineReport
from slam.algorithm.submaps import KeyframeDecisions, KeyframeStep, SubmapPoints, SubmapRecord

if TYPE_CHECKING:
    from slam.algorithm.merge.relocalise import Relocalisation, Relocaliser

logger = logging.getLogger(__name__)


class SlamPipeline:
    """Odometry, keyframing, neural mapping, loop closure, pose graph and remapping."""

    def __init__(
        self,
        cfg: PipelineConfig,
        sensor: str,
        odometry: Odometry,
        neural_map,
        loop_detector: LoopDetector | None = None,
        relocaliser: Relocaliser | None = None,
        encode: bool = True,
    ) -> None:
        keep_large_allocations_apart()
        self.cfg = cfg
        self.sensor = sensor
        self.odometry = odometry
        self.map = neural_map
        self.keyframer = KeyframeDecisions(cfg.submaps)  # the main thread's
        self.submap_points = SubmapPoints(cfg.submaps, encode)  # the submap worker's
        self._surface_full = False  # the last submap job's SubmapPoints.surface_full
        self.graph = PoseGraph(cfg.pose_graph)
        self.loop_detector = (
            loop_detector
            if loop_detector is not None
            else make_loop_detector(cfg.loop_closure, sensor)
        )
        self.remapper = Remapper(cfg.remap, neural_map)
        self.localisation = (  # the submap worker's
            MapLocalisation(relocaliser)
            if relocaliser is not None and self.loop_detector is not None
            else None
        )
        self.encode = encode
        self.submaps: dict[int, object] = {}  # the map worker's (complete after finish())
        self.records: dict[int, SubmapRecord] = {}  # the submap worker's
        self.executor = Executor(threaded=cfg.map_worker)
        self.view = self.executor.view
        self._num_accepted = 0  # the submap worker's
        self._published_inliers: dict[tuple[int, int], bool] = {}  # the submap worker's
        self.frames = FrameTrack()  # the main thread's
        self._closed_count = 0
        self._finished = False

    # --- per frame ----------------------------------------------------------------------------

    @staticmethod
    def _map_frame(frame: Frame, odometry: OdometryResult) -> Frame:
        """The frame whose points go into the map: the odometry's corrected points (e.g.
        KISS-ICP's deskewed scan) for frames without normals of their own."""
        if frame.normals is not None or odometry.points is None:
            return frame
        points = odometry.points
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
        timings = self.executor.main_timings
        start = clock()
        odometry = self.odometry.register(frame)
        T_W_S_odometry = np.asarray(odometry.T_W_S, dtype=np.float64)
        timings.book("odometry", start)

        map_frame = self._map_frame(frame, odometry)
        step = self.keyframer.decide(map_frame, T_W_S_odometry, self._surface_full)
        current = step.current
        assert current is not None and step.T_A_S is not None
        covariance = None
        if step.opened:
            self.view.add_anchor(current.submap_id, current.T_W_A_odometry)
            if odometry.covariance is not None:
                covariance = np.array(odometry.covariance, dtype=np.float64)
            self.odometry.restart_covariance()
        queued = map_frame.without_images()  # the submap worker absorbs points and normals
        if step.closing is not None:
            self._closed_count += 1
        job = self.executor.submit_frame(
            self._submap_job, step, queued, covariance, frame.index, closes=step.closing is not None
        )
        if not self.keyframer.decides_from_poses:  # the next decision needs this frame's points
            self._surface_full = job_result(job).surface_full

        self.frames.add(
            current.submap_id, step.T_A_S, T_W_S_odometry, frame.timestamp, frame.T_W_S_gt
        )

        result = FrameResult(
            index=frame.index,
            T_W_S_odometry=T_W_S_odometry,
            T_W_S=self.view.pose(current.submap_id) @ step.T_A_S,
            submap_id=current.submap_id,
        )
        if step.closing is not None:
            result.closed_submap_id = step.closing.submap_id
        result.loops, result.remap, result.loop_added, result.relocalised = self.view.take_news()
        result.odometry_s = timings.wall_s["odometry"][-1]
        result.frame_s = time.perf_counter() - start[0]
        timings.wall_s["frame"].append(result.frame_s)
        return result

    def _submap_job(
        self,
        step: KeyframeStep,
        frame: Frame | None,
        covariance: np.ndarray | None,
        frame_index: int,
    ) -> SubmapJobResult:
        """One frame on the submap worker: its points into its submap, its anchor into the
        graph when it opened one, and the submap it closed through loop detection to the map
        worker."""
        start = clock()
        closed = self.submap_points.absorb(step, frame)
        current = step.current
        if step.opened and current is not None and current.submap_id not in self.graph:
            self.graph.add_anchor(current.submap_id, current.T_W_A_odometry, covariance)
            gravity = self.cfg.pose_graph.gravity
            anchored = self.localisation is not None and self.localisation.holds_attitude
            measure = gravity.enabled and self.odometry.drifts and not anchored
            if measure and frame is not None:  # the anchor's scan
                up = measure_up(frame, self.graph.up_in(current.submap_id), gravity)
                if up is not None:
                    self.graph.add_gravity(current.submap_id, up)
        self.executor.submap_timings.book("keyframing", start)
        snapshot = None if closed is None else self._on_submap_closed(closed, frame_index)
        return SubmapJobResult(snapshot, self.submap_points.surface_full)

    # --- submap boundaries --------------------------------------------------------------------

    def _on_submap_closed(self, record: SubmapRecord, frame_index: int) -> GraphSnapshot:
        """Loop detection, loop edges and the map job of a closed submap (submap worker)."""
        timings = self.executor.submap_timings
        start = clock()
        candidates: list[LoopCandidate] = []
        if self.loop_detector is not None:
            candidates = self.loop_detector.process(
                record, self.graph.poses(), self.graph.relative_covariance
            )
        t = timings.book("loop_detection", start)
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
        timings.book("pose_graph", t)
        relocalised = None
        if self.localisation is not None:
            assert self.loop_detector is not None
            start = clock()
            relocalised, moved = self.localisation.on_submap_closed(
                record, self.graph, self.loop_detector.descriptors.get(record.submap_id)
            )
            added |= moved
            self.submap_points.placed = self.localisation.placement is not None
            timings.book("relocalisation", start)

        # the keyframe's images were for loop detection; the map only needs the points
        record.keyframe = None
        self.records[record.submap_id] = record
        remap = None
        if not self.encode:  # localisation only: the run keeps no map
            record.points_A = record.normals_A = np.zeros((0, 3))
            return self._snapshot(candidates, added, remap, relocalised)
        T_W_A = self.graph.pose(record.submap_id).copy()
        remap_poses = self.graph.poses() if added else None
        job = self.executor.submit_map_job(self._map_job, record, T_W_A, remap_poses, frame_index)
        if not self.executor.threaded:  # the job ran already: its remap is this frame's news
            remap = job.result()
            remap = remap if remap is not None and remap.num_moved > 0 else None
        return self._snapshot(candidates, added, remap, relocalised)

    def _snapshot(
        self,
        candidates: list[LoopCandidate],
        added: bool,
        remap: RemapEvent | None = None,
        relocalised: Relocalisation | None = None,
    ) -> GraphSnapshot:
        """The graph as the main thread will see it (taken by the graph's owner): the inlier
        decisions that changed since the last snapshot."""
        changed = {}
        for edge in self.graph.loops:
            key = (edge.i, edge.j)
            if self._published_inliers.get(key) != edge.inlier:
                changed[key] = self._published_inliers[key] = edge.inlier
        snapshot = GraphSnapshot(
            self.graph.poses(), candidates, changed, self._num_accepted, added, remap, relocalised
        )
        if self.localisation is not None:
            snapshot.map_anchored = self.localisation.anchored(self.graph)
        return snapshot

    def _map_job(
        self,
        record: SubmapRecord,
        T_W_A: np.ndarray,
        remap_poses: dict[int, np.ndarray] | None,
        frame_index: int,
    ) -> RemapEvent | None:
        """Encode and fuse a closed submap, then remap if the graph moved (map worker); returns
        the remapping pass, if one ran."""
        timings = self.executor.map_timings
        start = clock()
        self._encode(record, T_W_A)
        start = timings.book("mapping", start)
        event = None
        if remap_poses is not None:
            event = self.remapper.apply(self.submaps, remap_poses, frame_index)
            timings.book("remap", start)
        release_freed_memory()
        self.executor.publish_map(self.map, event)
        return event

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

    # --- end of the sequence ------------------------------------------------------------------

    def finish(self) -> RemapEvent | None:
        """Close the last submap, run the final batch optimisation and remap."""
        if self._finished:
            return None
        last_index = len(self.frames) - 1
        step = self.keyframer.decide_finish()
        self.odometry.close()
        if step is not None:
            self._closed_count += 1
            self.executor.submit_frame(self._submap_job, step, None, None, last_index, closes=True)
        self.executor.close_submap_worker()
        if self.loop_detector is not None:  # no submap is left to verify
            self.loop_detector.release()
        timings = self.executor.main_timings
        t = clock()
        self.graph.optimize_batch()
        timings.book("pose_graph", t)
        self.executor.close_map_worker()
        t = clock()
        remap = self.remapper.apply(self.submaps, self.graph.poses(), -1)
        release_freed_memory()
        timings.book("remap", t)
        self.view.apply(self._snapshot([], False))
        self._finished = True
        return remap

    def abort(self) -> None:
        """Stop the workers without running their queued jobs (an interrupted or failed run);
        the pipeline cannot go on after it."""
        self._finished = True
        self.executor.abort()
        self.odometry.close()

    # --- results ------------------------------------------------------------------------------

    @property
    def finished(self) -> bool:
        """:meth:`finish` ran (every result is final) or :meth:`abort` did (the run ended)."""
        return self._finished

    def slam_poses(self) -> np.ndarray:
        """(N, 4, 4) current SLAM estimates of the frames processed so far (the main thread's
        :attr:`view` of the anchors: exact after :meth:`drain` and :meth:`finish`)."""
        return self.frames.slam_poses(
            self.view.poses(),
            self.cfg.pose_graph.frames_follow_next_anchor,
            rigid=self.view.map_anchored,
        )

    def drain(self) -> None:
        """Wait for both workers: the graph view, the loop candidates and the map then reflect
        every submap closed so far."""
        self.executor.sync()

    @property
    def loop_candidates(self) -> list[LoopCandidate]:
        """Every loop candidate examined, as far as the main thread knows (see :attr:`view`)."""
        return self.view.loop_candidates

    def accepted_loops(self) -> list[LoopCandidate]:
        return [c for c in self.loop_candidates if c.accepted]

    @property
    def num_closed_submaps(self) -> int:
        """Submaps closed so far (encoded or queued for the map worker)."""
        return self._closed_count

    @property
    def num_accepted_loops(self) -> int:
        """Loop edges added to the pose graph, as far as the main thread knows."""
        return self.view.num_accepted

    def anchor_poses(self) -> dict[int, np.ndarray]:
        """Current estimate of every submap anchor, ``{submap_id: T_W_A}`` (the main thread's
        :attr:`view`: exact after :meth:`drain` and :meth:`finish`)."""
        return self.view.poses()

    @property
    def relocalisation(self) -> Relocalisation | None:
        """Where the session was placed in the stored map, as far as the main thread knows
        (None without a relocaliser, or before a submap verified)."""
        return self.view.relocalisation

    @property
    def map_anchored(self) -> dict[int, tuple[int, ...]]:
        """Submaps anchored in the stored map by a registration the graph keeps, each with the
        stored submaps it was registered to, as far as the main thread knows
        (:mod:`slam.algorithm.localisation`)."""
        return self.view.map_anchored

    def request_map_snapshots(self, request: MapSnapshotRequest) -> None:
        """Have the map worker publish the map after each job for a viewer (:meth:`latest_map`),
        with the meshes ``request`` asks for. Before the first frame."""
        self.executor.request_map_snapshots(request)

    def latest_map(self) -> MapSnapshot | None:
        """The map as the latest finished map job left it (see :meth:`request_map_snapshots`);
        never waits for the workers."""
        return self.executor.latest_map()

    def map_voxels(self) -> tuple[np.ndarray, np.ndarray]:
        """What a viewer shows of the map's voxels now, exactly: their centres and weights
        (waits for the workers; booked as the ``map_logging`` stage)."""
        self.drain()
        start = clock()
        centers, weights = self.map.voxel_centers()
        self.executor.main_timings.book("map_logging", start)
        return np.asarray(centers), np.asarray(weights, dtype=np.float64)

    @property
    def timings_s(self) -> dict[str, list[float]]:
        """Wall seconds of every call of each stage, over all threads (the workers' stages once
        :meth:`finish` stopped them)."""
        return self.executor.timings()[0]

    @property
    def stage_cpu_s(self) -> dict[str, float]:
        """CPU seconds of the thread that ran each stage (KISS-ICP's own pool is not counted)."""
        return self.executor.timings()[1]

    def report(self) -> PipelineReport:
        """The results and statistics metrics need (after :meth:`finish`)."""
        known = self.frames.gt_poses_where_known()
        return PipelineReport(
            num_frames=len(self.frames),
            odometry_poses=self.frames.odometry_poses(),
            slam_poses=self.slam_poses(),
            gt_poses=None if known is None else known[0],
            timestamps=self.frames.timestamps(),
            loop_candidates=list(self.loop_candidates),
            remap_events=list(self.remapper.events),
            submap_frame_counts=self.frames.submap_frame_counts(),
            neural_map=self.map,
            submaps=list(self.submaps.values()),
            timings_s=self.timings_s,
            stage_cpu_s=self.stage_cpu_s,
        )
