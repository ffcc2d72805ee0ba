"""``slam.run --map RUN_DIR --localise``: a run localised in a stored map, frame by frame.

The room runs come from the session fixture ``room_sessions`` (tests/conftest.py): ``a`` is the
first half of a lap of a generated room, ``localised`` the second half localised in ``a``'s map
(it starts where ``a`` ended, so inside the map), ``inside`` a stretch in the middle of ``a``
localised in its map with a recording. The pose graph's side (map priors hold a
drifting chain on the truth, a wrong one is rejected) is in tests/test_pose_graph.py."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from slam.algorithm.loops.place import _rigid_fit
from slam.app.cli import main as run_main
from slam.run_folder.trajectory_io import read_kitti
from tests.helpers import LIDAR_ARGS, ROOM_SESSION_ARGS, assert_error_line, call_main

# measured: 1.1 cm mean, 1.5 cm worst frame (the map's own poses are ~0.5 cm off the truth)
MAP_FRAME_MEAN_BOUND_M = 0.015
MAP_FRAME_WORST_BOUND_M = 0.02


def _error_in_map_alignment(map_run: Path, run: Path) -> np.ndarray:
    """Per-frame position error of ``run``'s poses against its truth carried into the map's
    frame by the alignment of the map's own truth onto the map's poses."""
    truth = _rigid_fit(
        read_kitti(map_run / "poses_gt.kitti.txt")[:, :3, 3],
        read_kitti(map_run / "poses_slam.kitti.txt")[:, :3, 3],
        False,
    )
    poses = read_kitti(run / "poses_slam.kitti.txt")[:, :3, 3]
    gt = read_kitti(run / "poses_gt.kitti.txt")[:, :3, 3]
    return np.linalg.norm(gt @ truth[:3, :3].T + truth[:3, 3] - poses, axis=1)


def test_localised_poses_are_in_the_maps_frame_with_a_status_per_frame(room_sessions):
    run, stored = room_sessions["localised"], room_sessions["a"]
    error = _error_in_map_alignment(stored, run)
    assert len(error) == 60 and error.mean() < MAP_FRAME_MEAN_BOUND_M, error.mean()
    assert error.max() < MAP_FRAME_WORST_BOUND_M, error.max()
    rows = (run / "localisation.csv").read_text().splitlines()
    assert rows[0] == "frame,timestamp,submap,status" and len(rows) == 61
    statuses = [row.split(",")[3] for row in rows[1:]]
    assert set(statuses) <= {"anchored", "odometry"}
    metrics = json.loads((run / "metrics.json").read_text())
    summary = metrics["localisation"]
    assert summary["frames"] == 60
    assert summary["frames_anchored"] == statuses.count("anchored") >= 20
    assert summary["fraction_anchored"] == summary["frames_anchored"] / 60
    # the gaps are exactly the odometry-only frames after the placement
    odometry = [int(row.split(",")[0]) for row in rows[1:] if row.endswith(",odometry")]
    in_gaps = [f for first, last in summary["coverage_gaps"] for f in range(first, last + 1)]
    assert in_gaps == odometry[summary["frames_before_placement"] :]
    # localisation only: no map, mesh or merge, no session folder
    for name in ("map.npz", "mesh.ply", "sessions.csv", "session"):
        assert not (run / name).exists(), name
    assert json.loads((run / "run_status.json").read_text())["state"] == "finished"


def test_a_run_starting_inside_the_map_is_placed_by_its_first_submap(room_sessions):
    """Where the map ends (``localised``, ``b``) and in its middle (``inside``)."""
    for name in ("localised", "b", "inside"):  # --localise and the continuation alike
        placed = json.loads((room_sessions[name] / "metrics.json").read_text())["relocalisation"]
        assert placed["relocalised"] and placed["submaps_tried"] == 1, placed
        assert placed["submap"] == 0 and placed["submap_frames"][0] == 0
    for name in ("localised", "inside"):
        summary = json.loads((room_sessions[name] / "metrics.json").read_text())["localisation"]
        rows = [row.split(",") for row in _rows(room_sessions[name])]
        first_submap_frames = [row for row in rows if row[2] == rows[0][2]]
        # at most the first submap's frames come before the placing one: here none
        assert summary["frames_before_placement"] == 0 < len(first_submap_frames), summary
        # known when the second submap closes, at the third's first frame (the worker's result
        # reaches the run one submap late)
        ids = list(dict.fromkeys(row[2] for row in rows))
        third = next(row for row in rows if row[2] == ids[2])
        assert summary["placed_at_frame"] == int(third[0]), summary


def _rows(run: Path) -> list[str]:
    return (run / "localisation.csv").read_text().splitlines()[1:]


def _logged(recording: Path, entity: str, component: str) -> list[tuple[int, list]]:
    """``(frame, value)`` of every temporal row of ``entity``'s ``component`` in a recording."""
    from rerun.chunk import RrdReader

    reader = RrdReader(recording)
    rows = []
    for chunk in reader.stream(store=reader.recordings()[0]):
        if chunk.entity_path.lstrip("/") != entity or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        columns = dict(zip(batch.schema.names, batch.columns, strict=True))
        rows += zip(columns["frame"].to_pylist(), columns[component].to_pylist(), strict=True)
    return sorted(rows, key=lambda row: row[0])


def test_the_recording_shows_which_stored_submaps_hold_the_run(room_sessions):
    """The stored mesh, the sensor at every frame, segments from each map-anchored live anchor
    to the stored anchors it was registered to (growing as they are added), and each frame's
    status."""
    from slam.app.merge_cli import load_run
    from slam.app.recording_summary import summarize_recording

    run, stored = room_sessions["inside"], room_sessions["a"]
    recording = run / "recording.rrd"
    summary = summarize_recording(recording)
    assert summary.entities["world/stored_map/mesh"].static_rows == 1
    assert summary.rows("world/sensor") == 30
    anchors = load_run(stored)[0].session.anchor_poses()
    stored_anchors = np.array([T[:3, 3] for T in anchors.values()])
    frames = _logged(recording, "world/stored_map/anchoring", "LineStrips3D:strips")
    counts = [len(strips) for _, strips in frames]
    assert counts == sorted(counts) and counts[0] < counts[-1], counts  # added as they come
    final = np.array(frames[-1][1])  # (segments, 2, 3): after the final optimisation
    to_stored = np.linalg.norm(final[:, 1, None] - stored_anchors[None], axis=2).min(axis=1)
    assert to_stored.max() < 1e-5, to_stored
    # each segment starts at an anchored live submap's anchor: the pose of its first frame
    poses = read_kitti(run / "poses_slam.kitti.txt")[:, :3, 3]
    rows = [row.split(",") for row in _rows(run)]
    first_frames: dict[str, int] = {}
    for k, (_, _, submap, status) in enumerate(rows):
        if status == "anchored":
            first_frames.setdefault(submap, k)
    distance = np.linalg.norm(final[:, 0, None] - poses[list(first_frames.values())], axis=2)
    assert distance.min(axis=1).max() < 1e-4  # every segment starts at an anchored live anchor
    assert distance.min(axis=0).max() < 1e-4  # every anchored live submap has its segments
    status = _logged(recording, "metrics/counts/map_anchored", "Scalars:scalars")
    assert len(status) == 30 and {value[0] for _, value in status} == {0.0, 1.0}
    placed_at = json.loads((run / "metrics.json").read_text())["localisation"]["placed_at_frame"]
    assert all(value[0] == float(frame >= placed_at) for frame, value in status), status


def test_every_later_submap_is_registered_to_the_map(room_sessions):
    """After the placement each closed submap is registered to the stored map: a submap the
    map covers is anchored, one it does not is reported once as a gap."""
    run = room_sessions["localised"]
    summary = json.loads((run / "metrics.json").read_text())["localisation"]
    submaps = {int(row.split(",")[2]) for row in (run / "localisation.csv").read_text().split()[1:]}
    not_registered = sum(summary["submaps_not_registered"].values())
    # the placing submap's own registration counts; every other submap was tried
    assert summary["submaps_registered"] + not_registered == len(submaps)
    assert summary["submaps_registered"] >= 2
    left = (run / "run.log").read_text().count("left the map at frames")
    assert left == len(summary["coverage_gaps"])


def test_localise_needs_a_usable_map(room_sessions, tmp_path: Path):
    data, out = tmp_path / "data", tmp_path / "out"
    common = ("demo", "--root", str(data), "--no-viz", "--no-progress", "--out", str(out))
    result = call_main(run_main, [*common, "--localise", *ROOM_SESSION_ARGS])
    assert result.returncode == 2
    assert_error_line(result, "--localise needs --map")
    coarse = room_sessions["coarse"]
    result = call_main(run_main, [*common, "--map", str(coarse), "--localise"])
    assert_error_line(result, "voxel size", str(coarse), "mapping.voxel_size_m=0.15")
    corrupt = tmp_path / "corrupt"
    corrupt.mkdir()
    (corrupt / "map.npz").write_bytes(b"PK\x03\x04 not a map")
    result = call_main(run_main, [*common, "--map", str(corrupt), "--localise"])
    assert_error_line(result, "map.npz")
    assert not out.exists() and not data.exists()


def test_localise_in_a_map_sharing_no_place_ends_with_one_line(lidar_run, tmp_path: Path):
    """A stretch of the generated street that the map never saw: the run goes on with
    odometry, then ends with one line (its poses are not in the map's frame)."""
    out = tmp_path / "out"
    args = [a if a != "0:30" else "70:85" for a in LIDAR_ARGS]
    result = call_main(
        run_main, [*args, "--map", str(lidar_run.folder), "--localise", "--out", str(out)]
    )
    assert result.returncode == 1
    assert_error_line(result, "never placed", str(lidar_run.folder), str(out))
    rows = (out / "localisation.csv").read_text().splitlines()[1:]
    assert len(rows) == 15 and all(row.endswith(",odometry") for row in rows)


def test_a_submap_seeing_the_stored_surface_only_in_part_constrains_nothing(room_sessions):
    """After the placement, a live submap that lies on the stored surface only in part must not
    become a prior: such a registration converges where the unmatched part pulls it. A stored
    submap's own decoded surface, at its own pose, is accepted with a covariance no tighter than
    its residual spread; the same surface with about 45 % of its points replaced by points
    scattered through its bounding box (an overlap the merge's own gate still passes) is
    rejected as a partial overlap."""
    from slam.algorithm.merge.config import LocaliseConfig, MergeConfig
    from slam.algorithm.merge.map_constraints import MapConstraints
    from slam.algorithm.merge.surface import SurfaceDecoder
    from slam.app.continue_map import load_map_folder
    from slam.assembly.config import load_run_config

    folder = room_sessions["a"]
    stored, stored_map = load_map_folder(folder, load_run_config(folder / "config.yaml"))
    poses = stored.session.anchor_poses()
    submaps = {s.submap_id: s for s in stored.submaps if s.submap_id in poses}
    merge, localise = MergeConfig(), LocaliseConfig(max_map_submaps=1, ambiguity_check=False)
    decoder = SurfaceDecoder(stored_map, merge.surface_max_points, merge.surface_subdivisions)
    constraints = MapConstraints(submaps, poses, decoder, stored_map.voxel_size_m, merge, localise)
    submap = max(submaps.values(), key=lambda s: len(s.original.keys))
    surface_A = decoder(("map", submap.submap_id), submap)[0]  # the reference's own surface
    T_M_A = poses[submap.submap_id]

    full = constraints.register(100, surface_A, T_M_A)
    assert full is not None and full.accepted, full and full.reason
    assert full.scores["inlier_fraction"] > 0.9
    sigma_m = np.sqrt(np.linalg.eigvalsh(full.covariance[3:, 3:]).min())
    assert sigma_m >= full.scores["residual_sigma_m"]

    rng = np.random.default_rng(0)
    kept = surface_A[rng.random(len(surface_A)) < 0.55]
    low, high = surface_A.min(axis=0), surface_A.max(axis=0)
    scattered = rng.uniform(low, high, size=(len(surface_A) - len(kept), 3))
    partial = constraints.register(101, np.vstack([kept, scattered]), T_M_A)
    assert partial is not None
    assert merge.min_inlier_fraction <= partial.scores["inlier_fraction"]
    assert partial.scores["inlier_fraction"] < localise.min_inlier_fraction
    assert not partial.accepted and partial.reason.startswith("partial overlap")


def test_the_anchors_gravity_is_left_to_the_map_while_it_holds_the_run(room_sessions):
    """Once placed, while the last closed submap is anchored in the stored map, the map's
    priors hold the attitude and a new anchor needs no gravity measurement; a submap the map
    does not cover hands it back to gravity, and ``gravity_while_anchored`` always does."""
    from slam.algorithm.graph.pose_graph import PoseGraph
    from slam.algorithm.localisation import NOT_COVERED, MapLocalisation
    from slam.algorithm.merge.config import LocaliseConfig
    from slam.algorithm.merge.relocalise import Relocaliser
    from slam.algorithm.merge.surface import SurfaceDecoder
    from slam.algorithm.submaps import SubmapRecord
    from slam.app.continue_map import load_map_folder
    from slam.assembly.config import load_run_config

    folder = room_sessions["a"]
    cfg = load_run_config(folder / "config.yaml")
    stored, stored_map = load_map_folder(folder, cfg)
    submap = max(
        (s for s in stored.submaps if s.submap_id in stored.session.descriptors),
        key=lambda s: len(s.original.keys),
    )
    decoder = SurfaceDecoder(stored_map, 20000, 2)
    surface_A = decoder(("map", submap.submap_id), submap)[0]
    descriptor = stored.session.descriptors[submap.submap_id]
    for measure_anyway in (False, True):
        localise = LocaliseConfig(gravity_while_anchored=measure_anyway)
        localisation = MapLocalisation(Relocaliser(stored, stored_map, localise=localise))
        graph = PoseGraph(cfg.pose_graph)
        graph.add_anchor(0, np.eye(4))
        assert not localisation.holds_attitude  # not placed yet
        placing = SubmapRecord(0, [0], np.eye(4), 0.0, points_A=surface_A)
        placed, _ = localisation.on_submap_closed(placing, graph, descriptor)
        assert placed is not None and placed.map_submap_id == submap.submap_id
        assert localisation.holds_attitude is not measure_anyway
        graph.add_anchor(1, np.eye(4))
        far = SubmapRecord(1, [1], np.eye(4), 0.0, points_A=surface_A + np.array([500.0, 0.0, 0.0]))
        localisation.on_submap_closed(far, graph, None)
        assert localisation.constraints[-1].reason == NOT_COVERED
        assert not localisation.holds_attitude


def test_the_maps_surfaces_are_decoded_under_the_runs_thread_budget(room_sessions):
    """``--localise`` decodes every stored surface before the first frame: under the run's
    thread budget (torch's default pool spans every core, and on a busy machine its threads
    wait for each other at every operation), on the threads of the whole-map mesh, each
    surface what decoding it alone gives."""
    import torch

    from slam.algorithm.merge.surface import SurfaceDecoder
    from slam.app.continue_map import continued_map, load_map_folder
    from slam.assembly.config import load_run_config
    from slam.assembly.threads import plan_thread_budget

    folder = room_sessions["a"]
    cfg = load_run_config(folder / "config.yaml")
    cfg.threads, cfg.map_worker = 2, True
    budget = plan_thread_budget(cfg.threads, cfg.map_worker)
    previous = load_map_folder(folder, cfg)
    before = torch.get_num_threads()
    torch.set_num_threads(budget.budget + 1)
    try:
        relocaliser = continued_map(previous, folder, cfg, localise_only=True).relocaliser
        assert torch.get_num_threads() == budget.torch < budget.budget + 1
    finally:
        torch.set_num_threads(before)
    assert budget.mesh_threads > 1 and relocaliser.decode_seconds > 0
    stored, stored_map = previous
    merge = relocaliser.cfg
    alone = SurfaceDecoder(stored_map, merge.surface_max_points, merge.surface_subdivisions)
    poses = stored.session.anchor_poses()
    decoded = [s for s in stored.submaps if s.submap_id in poses]
    assert len(decoded) > 1
    for submap in decoded:
        key = ("map", submap.submap_id)
        points, normals = relocaliser.constraints._decoder(key, submap)
        expected = alone(key, submap)
        assert len(points) > 100
        np.testing.assert_allclose(points, expected[0], atol=1e-6)
        np.testing.assert_allclose(normals, expected[1], atol=1e-6)
