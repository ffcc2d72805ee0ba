"""The app's recorder: what a run hands to the viewer, at O(1) per frame, and nothing at all for
the null logger.

A short stretch of the generated room runs through the real pipeline (drifting ground-truth
odometry, real keyframing, map and RGB-D loop detector) with one extra accepted loop edge, so
that the optimised trajectory must be recomputed once.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from frontends.sources import make_source
from slam.algorithm.loops.registry import make_loop_detector
from slam.algorithm.pipeline import SlamPipeline
from slam.algorithm.viz import Logger, NullLogger
from slam.app.recorder import RunRecorder, make_recorder
from slam.assembly.builders import build_map
from tests.pipeline_setups import ROOM, FalseLoopInjector, room_config, room_odometry

WAIT_S = 20.0
"""How long the held map worker waits for the test before it gives up."""


class CapturingLogger(Logger):
    """Keeps a copy of everything it is given (a recording, in memory)."""

    def __init__(self) -> None:
        self.trajectories: dict[str, list[np.ndarray]] = {}
        self.loops: list[tuple[list, list]] = []
        self.maps: list[tuple[np.ndarray, np.ndarray, object]] = []
        self.metrics: list[dict[str, float]] = []

    def set_time(self, frame_index, timestamp_s):
        pass

    def log_scan(self, points_W, colors=None, T_W_S=None):
        pass

    def log_sensor(self, T_W_S, intrinsics=None, rgb=None, depth_m=None):
        pass

    def log_trajectory(self, name, positions_W):
        self.trajectories.setdefault(name, []).append(np.array(positions_W))

    def log_loop_closures(self, accepted, rejected=()):
        self.loops.append((list(accepted), list(rejected)))

    def log_map(self, voxel_centers_W, voxel_values, mesh=None):
        self.maps.append((voxel_centers_W, voxel_values, mesh))

    def log_metrics(self, **scalars):
        self.metrics.append(scalars)


@pytest.fixture(scope="module")
def stretch():
    """30 frames (every second one) of the room lap."""
    return make_source(
        "generated",
        **ROOM,
        frames=slice(0, 60, 2),
        loader_options={"depth_options": {"stride": 2}},
    )


def _pipeline(map_worker: bool = True) -> tuple[SlamPipeline, object]:
    # submaps of 4 frames: the injected loop (at the 5th close) is news at the 6th, frame 24
    cfg = room_config(max_frames=4)
    cfg.map_worker = map_worker
    detector = FalseLoopInjector(
        make_loop_detector(cfg.loop_closure, "rgbd"), at_submap=4, wrong_by_m=0.05
    )
    pipeline = SlamPipeline(
        cfg.pipeline_config(), "rgbd", room_odometry(), build_map(cfg), loop_detector=detector
    )
    return pipeline, cfg


def test_recorder_grows_trajectories_by_one_and_recomputes_them_after_a_loop(stretch):
    pipeline, cfg = _pipeline(map_worker=False)  # inline: every map job is done at its close
    viz = CapturingLogger()
    every_second = {"mesh_every_submaps": 2, "mesh_time_share": 1.0}  # 1.0: no time limit
    recorder = make_recorder(pipeline, viz, cfg.viz.model_copy(update=every_second))
    assert isinstance(recorder, RunRecorder)
    loop_frames = 0
    for n, frame in enumerate(stretch, start=1):
        result = pipeline.process(frame)
        recorder.frame(frame, result)
        odometry = viz.trajectories["odometry"][-1]
        optimized = viz.trajectories["optimized"][-1]
        assert len(odometry) == len(optimized) == len(viz.trajectories["gt"][-1]) == n
        np.testing.assert_array_equal(odometry[-1], result.T_W_S_odometry[:3, 3])
        if result.loop_added:
            loop_frames += 1
            # every frame's estimate moved: the whole track is the graph's current one
            np.testing.assert_allclose(optimized, pipeline.slam_poses()[:, :3, 3], atol=1e-12)
            assert np.abs(optimized[:-1] - viz.trajectories["optimized"][-2]).max() > 1e-4
        else:
            np.testing.assert_array_equal(optimized[-1], result.T_W_S[:3, 3])
    assert loop_frames == 1
    pipeline.finish()
    mesh = pipeline.map.extract_mesh()
    recorder.finish(mesh)
    np.testing.assert_allclose(
        viz.trajectories["optimized"][-1], pipeline.slam_poses()[:, :3, 3], atol=1e-12
    )
    accepted, _ = viz.loops[-1]
    assert len(accepted) + len(viz.loops[-1][1]) == len(pipeline.loop_candidates) >= 1
    # a mesh every second closed submap and at the end; voxel centres at every close
    assert [m[2] is not None for m in viz.maps][:3] == [False, True, False]
    # the final map: the mesh the run extracted for its outputs, not one more extraction
    assert viz.maps[-1][2] is mesh and len(viz.maps[-1][0]) == pipeline.map.num_voxels
    final = viz.metrics[-1]
    assert final["map_voxels"] == pipeline.map.num_voxels
    assert final["ate_slam_m"] > 0 and final["ate_odometry_m"] > 0
    # the map worker published after each of its jobs (the last close's included), and the
    # recorder logged each published map during the run and the exact one at the end
    closed = pipeline.num_closed_submaps
    assert len(pipeline.timings_s["map_logging"]) == closed + 1
    assert len(viz.maps) == closed


def test_recorder_logs_the_published_map_without_waiting_for_the_map_worker(stretch):
    """With the map worker held up, frames and submap closes go on and nothing is logged of
    the map until it publishes (a recorder that drained the workers would wait here)."""
    pipeline, cfg = _pipeline(map_worker=True)
    released = threading.Event()
    encode = pipeline.map.encode

    def held_encode(*args, **kwargs):
        assert released.wait(WAIT_S), "the recorder waited for the held map worker"
        return encode(*args, **kwargs)

    pipeline.map.encode = held_encode
    viz = CapturingLogger()
    recorder = make_recorder(pipeline, viz, cfg.viz)
    start = time.perf_counter()
    for frame in list(stretch)[:12]:
        recorder.frame(frame, pipeline.process(frame))
    assert time.perf_counter() - start < WAIT_S
    assert pipeline.num_closed_submaps == 2 and viz.maps == []
    released.set()
    pipeline.finish()
    recorder.finish(None)
    assert len(viz.maps) == 1 and len(viz.maps[0][0]) == pipeline.map.num_voxels


def test_null_logger_gets_a_recorder_that_computes_nothing(stretch):
    pipeline, cfg = _pipeline()
    recorder = make_recorder(pipeline, NullLogger(), cfg.viz)
    assert not isinstance(recorder, RunRecorder)
    for frame in list(stretch)[:12]:
        recorder.frame(frame, pipeline.process(frame))
    pipeline.finish()
    recorder.finish(None)
    assert pipeline.num_closed_submaps >= 2
    assert pipeline.timings_s["map_logging"] == []  # no snapshot, so no mesh, was taken
