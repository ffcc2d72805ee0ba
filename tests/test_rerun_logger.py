"""RerunLogger writes a recording that Rerun's own reader loads with the expected entities."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from frontends.frame import Intrinsics
from slam.algorithm.viz import Logger, NullLogger
from slam.app.rerun_logger import RerunLogger, metric_entity, summarize_recording
from slam.app.rerun_trajectories import TRAJECTORY_MIN_RELOG_FRAMES

NUM_FRAMES = 24
LOOP_FRAMES = (11, 23)
INTRINSICS = Intrinsics(fx=120.0, fy=120.0, cx=80.0, cy=60.0, width=160, height=120)


def _drive(logger: Logger, rgbd: bool, scan_points: int = 6000) -> None:
    """A short sequence of calls as the pipeline makes them: a circle with two loop closures."""
    rng = np.random.default_rng(3)
    positions: list[np.ndarray] = []
    accepted: list[tuple[np.ndarray, np.ndarray]] = []
    for i in range(NUM_FRAMES):
        logger.set_time(i, 0.1 * i)
        angle = 2 * np.pi * i / 12
        T_W_S = np.eye(4)
        T_W_S[:3, :3] = trimesh.transformations.rotation_matrix(angle, [0, 0, 1])[:3, :3]
        T_W_S[:3, 3] = [3 * np.cos(angle), 3 * np.sin(angle), 0.0]
        positions.append(T_W_S[:3, 3].copy())
        logger.log_scan(rng.normal(size=(scan_points, 3)) + T_W_S[:3, 3])
        if rgbd:
            rgb = rng.integers(0, 255, (INTRINSICS.height, INTRINSICS.width, 3), dtype=np.uint8)
            depth = rng.uniform(0.5, 4.0, (INTRINSICS.height, INTRINSICS.width))
            logger.log_sensor(T_W_S, INTRINSICS, rgb=rgb, depth_m=depth.astype(np.float32))
        else:
            logger.log_sensor(T_W_S)
        logger.log_trajectory("odometry", np.asarray(positions))
        logger.log_trajectory("gt", np.asarray(positions) * 1.01)
        logger.log_metrics(odometry_ms=3.0 + i, ate_so_far_m=0.01 * i, loops=len(accepted))
        if i in LOOP_FRAMES:
            accepted.append((positions[0], positions[-1]))
            logger.log_trajectory("optimized", np.asarray(positions))
            logger.log_loop_closures(accepted, rejected=[(positions[1], positions[-2])])
            mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0 + 0.1 * i)
            voxels = rng.uniform(-3, 3, (500, 3))
            logger.log_map(voxels, rng.uniform(0, 20, 500), mesh=mesh)
    logger.close()


def test_null_logger_never_builds_what_only_a_recording_needs(tmp_path: Path) -> None:
    """The null logger takes every call and never calls the snapshot callables (voxel centres,
    meshes, the error so far), so a run without a viewer pays nothing for them; a recording
    logger does call them."""
    _drive(NullLogger(), rgbd=True)
    empty_map = (np.zeros((0, 3)), np.zeros(0), None)
    for logger, expected in (
        (NullLogger(), []),
        (RerunLogger(rrd_path=tmp_path / "rec.rrd"), ["map", "metrics"]),
    ):
        calls: list[str] = []
        logger.log_map_from(lambda calls=calls: calls.append("map") or empty_map)
        logger.log_metrics_from(lambda calls=calls: calls.append("metrics") or {"x": 1.0})
        logger.close()
        assert calls == expected


@pytest.mark.parametrize("rgbd", [False, True])
def test_recording_has_expected_entities(tmp_path: Path, rgbd: bool) -> None:
    path = tmp_path / "sub" / "rec.rrd"
    _drive(RerunLogger(rrd_path=path, scan_max_points=2000, voxel_size_m=0.2), rgbd=rgbd)
    summary = summarize_recording(path)
    assert summary.application_id == "neural-remap-slam"
    assert summary.num_blueprints >= 1
    # One downsampled scan per frame, never more points than the budget.
    assert summary.rows("world/scan") == NUM_FRAMES
    assert summary.entities["world/scan"].max_instances == 2000
    assert {"frame", "sensor_time"} <= summary.entities["world/scan"].timelines
    assert summary.rows("world/sensor") == NUM_FRAMES
    # Optimised trajectory after each loop closure, mesh versions, loop edges.
    assert summary.rows("world/trajectory/optimized") == len(LOOP_FRAMES)
    assert summary.rows("world/trajectory/odometry") >= NUM_FRAMES // TRAJECTORY_MIN_RELOG_FRAMES
    assert summary.rows("world/map/mesh") == len(LOOP_FRAMES)
    assert summary.rows("world/map/voxels") == len(LOOP_FRAMES)
    assert summary.entities["world/map/voxels"].max_instances == 500
    assert summary.entities["world/loop_closures"].max_instances == len(LOOP_FRAMES)
    assert summary.rows("world/loop_closures_rejected") == len(LOOP_FRAMES)
    for name in ("odometry_ms", "ate_so_far_m", "loops"):
        assert summary.rows(metric_entity(name)) == NUM_FRAMES
    assert metric_entity("odometry_ms") == "metrics/timing/odometry_ms"
    assert metric_entity("ate_so_far_m") == "metrics/error/ate_so_far_m"
    assert metric_entity("loops") == "metrics/counts/loops"
    assert metric_entity("loop_candidates") == "metrics/counts/loop_candidates"
    camera = ("world/sensor/camera/rgb", "world/sensor/depth_camera/depth")
    if rgbd:
        assert summary.entities["world/sensor/camera"].static_rows >= 1
        assert summary.entities["world/sensor/depth_camera"].static_rows >= 1
        assert all(summary.rows(entity) == NUM_FRAMES for entity in camera)
        assert any("EncodedImage" in c for c in summary.entities[camera[0]].components)
        assert any("DepthImage" in c for c in summary.entities[camera[1]].components)
        assert summary.num_blueprints == 2  # the camera view was added on the first image
    else:
        assert not any(entity in summary.entities for entity in camera)


def test_recording_verifies_with_rerun_cli(tmp_path: Path) -> None:
    path = tmp_path / "rec.rrd"
    _drive(RerunLogger(rrd_path=path), rgbd=True)
    result = subprocess.run(
        [sys.executable, "-m", "rerun", "rrd", "verify", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr[-2000:]


def test_two_recordings_in_one_process_stay_separate(tmp_path: Path) -> None:
    first = RerunLogger(rrd_path=tmp_path / "a.rrd")
    second = RerunLogger(rrd_path=tmp_path / "b.rrd")
    for i in range(3):
        first.set_time(i, float(i))
        first.log_scan(np.zeros((10, 3)))
    second.set_time(0, 0.0)
    second.log_metrics(loops=1)
    first.close()
    second.close()
    a, b = summarize_recording(tmp_path / "a.rrd"), summarize_recording(tmp_path / "b.rrd")
    assert a.rows("world/scan") == 3 and "world/scan" not in b.entities
    assert b.rows("metrics/counts/loops") == 1 and "metrics/counts/loops" not in a.entities


def _values_by_frame(path: Path, entity: str, component: str) -> dict[int, list]:
    """``{frame: value}`` of one component of one entity, read back with Rerun's reader."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    values: dict[int, list] = {}
    for chunk in reader.stream(store=reader.recordings()[0]):
        batch = chunk.to_record_batch()
        if chunk.entity_path.lstrip("/") != entity or component not in batch.schema.names:
            continue
        frames = batch.column("frame").to_pylist()
        values.update(zip(frames, batch.column(component).to_pylist(), strict=True))
    return values


def test_rows_sent_as_columns_keep_their_frame_and_values(tmp_path: Path) -> None:
    """Per-frame rows are held back and sent in columns (several sends, the last on close):
    each frame's pose and scalar read back at that frame, on all three timelines."""
    from slam.app.rerun_columns import FLUSH_FRAMES

    path = tmp_path / "rec.rrd"
    logger = RerunLogger(rrd_path=path)
    num_frames = 2 * FLUSH_FRAMES + 7
    for i in range(num_frames):
        logger.set_time(i, 0.1 * i)
        T_W_S = np.eye(4)
        T_W_S[:3, 3] = [i, 2.0 * i, -1.0]
        logger.log_sensor(T_W_S)
        logger.log_metrics(odometry_ms=100.0 + i)
    logger.close()
    translations = _values_by_frame(path, "world/sensor", "Transform3D:translation")
    scalars = _values_by_frame(path, metric_entity("odometry_ms"), "Scalars:scalars")
    assert sorted(translations) == sorted(scalars) == list(range(num_frames))
    for i in range(num_frames):
        assert translations[i] == [[i, 2.0 * i, -1.0]]
        assert scalars[i] == [100.0 + i]
    timelines = summarize_recording(path).entities["world/sensor"].timelines
    assert {"frame", "sensor_time", "log_time"} <= timelines


def test_flush_sends_the_held_rows_before_the_recording_closes(tmp_path: Path) -> None:
    """What a served run calls before it lingers: the rows held back reach the sinks (read
    back from the still open file, which has no footer yet)."""
    import warnings

    path = tmp_path / "rec.rrd"
    logger = RerunLogger(rrd_path=path)
    for i in range(5):
        logger.set_time(i, 0.1 * i)
        logger.log_sensor(np.eye(4))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the reader's note on a file without its footer
        logger.rec.flush()
        assert summarize_recording(path).rows("world/sensor") == 0
        logger.flush()
        logger.rec.flush()
        assert summarize_recording(path).rows("world/sensor") == 5
    logger.close()


def test_long_trajectory_is_throttled_but_moves_and_final_state_are_logged(
    tmp_path: Path,
) -> None:
    path = tmp_path / "rec.rrd"
    logger = RerunLogger(rrd_path=path, trajectory_relog_points=10)
    positions = np.cumsum(np.ones((100, 3)), axis=0)
    moved_at = (55, 77)
    for i in range(100):
        logger.set_time(i, float(i))
        if i in moved_at:
            positions = positions + 0.5  # an optimisation moves the whole trajectory
        logger.log_trajectory("odometry", positions[: i + 1])
    logger.close()
    rows = summarize_recording(path).rows("world/trajectory/odometry")
    # Every TRAJECTORY_MIN_RELOG_FRAMES frames up to 50 poses, then every ceil(N/10) frames
    # (~18 rows over 100 frames), plus the two moves and the pending last state.
    assert 15 <= rows <= 25

    logger = RerunLogger(rrd_path=tmp_path / "moves.rrd", trajectory_relog_points=1)
    for i in range(10):
        logger.set_time(i, float(i))
        logger.log_trajectory("optimized", positions[:50] + i)  # moved every frame
    logger.close()
    assert summarize_recording(tmp_path / "moves.rrd").rows("world/trajectory/optimized") == 10


def test_requires_a_sink() -> None:
    with pytest.raises(ValueError, match="needs a sink"):
        RerunLogger()


@pytest.mark.slow
def test_demo_recording_and_null_logger_give_identical_slam_outputs(
    demo_run: Path, demo_run_without_viewer: Path
) -> None:
    runs = {"no-viz": demo_run_without_viewer, "rrd": demo_run}
    for name in ("poses_odometry.kitti.txt", "poses_slam.kitti.txt", "loops.csv"):
        assert (runs["no-viz"] / name).read_bytes() == (runs["rrd"] / name).read_bytes(), name
    assert not (runs["no-viz"] / "recording.rrd").exists()

    metrics = json.loads((runs["rrd"] / "metrics.json").read_text())
    num_frames = metrics["num_frames"]
    summary = summarize_recording(runs["rrd"] / "recording.rrd")
    assert summary.rows("world/scan") == num_frames
    assert summary.rows("world/sensor") == num_frames
    assert summary.rows("world/sensor/camera/rgb") == num_frames
    assert summary.rows("world/sensor/depth_camera/depth") == num_frames
    assert summary.rows("world/trajectory/optimized") >= 1
    assert summary.rows("world/trajectory/gt") >= 1
    assert summary.rows("world/map/mesh") >= 2
    assert summary.rows("world/map/voxels") >= 2
    kept_loops = metrics["loops"]["graph_inliers"]
    assert kept_loops >= 1, "the short demo should close its lap"
    assert summary.entities["world/loop_closures"].max_instances >= 1
    assert summary.rows("metrics/timing/frame_ms") == num_frames
    assert summary.rows("metrics/error/ate_slam_m") >= 1


def test_mesh_decimation_keeps_the_surface_within_budget() -> None:
    from slam.app.rerun_logger import decimate_mesh

    sphere = trimesh.creation.icosphere(subdivisions=5)  # 20480 faces, radius 1
    colors = np.tile(np.array([[10, 200, 30]], np.uint8), (len(sphere.vertices), 1))
    vertices, faces, out_colors = decimate_mesh(sphere.vertices, sphere.faces, 2000, colors)
    assert 500 < len(faces) <= 2000
    assert faces.max() < len(vertices) and out_colors is not None
    assert len(out_colors) == len(vertices) and np.all(out_colors == [10, 200, 30])
    decimated = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    assert abs(decimated.area - sphere.area) / sphere.area < 0.1
    assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < 0.1
    same = decimate_mesh(sphere.vertices, sphere.faces, 30000)
    assert same[1] is not None and len(same[1]) == len(sphere.faces)


def test_mesh_decimation_sums_the_area_over_chunks_of_faces(monkeypatch) -> None:
    """The area that sets the clustering cell is summed over chunks of faces (a bounded memory
    peak on a whole map's mesh): chunks of 1,000 faces give trimesh's area and the same
    decimated mesh as one chunk."""
    from slam.app import mesh_decimation

    sphere = trimesh.creation.icosphere(subdivisions=5)
    decimated = []
    for faces_per_chunk in (1000, 1 << 30):
        monkeypatch.setattr(mesh_decimation, "FACES_PER_CHUNK", faces_per_chunk)
        area = mesh_decimation._area(np.asarray(sphere.vertices), np.asarray(sphere.faces))
        assert area == pytest.approx(sphere.area, rel=1e-9)
        decimated.append(mesh_decimation.decimate_mesh(sphere.vertices, sphere.faces, 2000))
    for chunked, whole in zip(*decimated, strict=True):
        np.testing.assert_array_equal(chunked, whole)


def test_stored_map_of_a_continued_run_is_shown_once(tmp_path: Path) -> None:
    import trimesh

    mesh_path = tmp_path / "mesh.ply"
    trimesh.creation.box(extents=(2.0, 1.0, 0.5)).export(mesh_path)
    shown = RerunLogger(rrd_path=tmp_path / "shown.rrd")
    shown.log_stored_map(mesh_path)
    shown.close()
    missing = RerunLogger(rrd_path=tmp_path / "missing.rrd")
    missing.log_stored_map(tmp_path / "no-such-mesh.ply")  # a warning, not an error
    missing.set_time(0, 0.0)
    missing.log_scan(np.zeros((10, 3)))
    missing.close()
    summary = summarize_recording(tmp_path / "shown.rrd")
    assert "world/stored_map/mesh" in summary.entities
    assert "world/stored_map/mesh" not in summarize_recording(tmp_path / "missing.rrd").entities


def test_colormap_table_matches_matplotlib_within_one_level() -> None:
    from matplotlib import colormaps

    from slam.app.rerun_images import colormap

    values = np.linspace(-0.2, 1.2, 1001)  # out of range values clip to the ends
    for name in ("viridis", "turbo"):
        exact = colormaps[name](np.clip(values, 0.0, 1.0), bytes=True)[:, :3].astype(int)
        table = colormaps[name](np.linspace(0.0, 1.0, 256), bytes=True)[:, :3].astype(int)
        step = np.abs(np.diff(table, axis=0))  # the colour change of one of the 256 levels
        assert np.abs(colormap(name, values).astype(int) - exact).max() <= step.max()
