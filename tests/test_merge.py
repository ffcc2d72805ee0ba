"""``python -m slam.merge`` and ``slam.run --map``: sessions of a generated room merge without
their scans, and a run continues another's map; a run merged with itself (or with a merged run
holding it) is refused; incompatible maps and runs without a shared place are refused.

Every run (short runs of one generated room) and the merge of the two sessions come from the
session fixture ``room_sessions`` (tests/conftest.py); the commands run in this process."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mapping.map_io import load_map
from slam.app.cli import main as run_main
from slam.app.merge_cli import main as merge_main
from slam.evaluation.cli import evaluate_run
from slam.run_folder.trajectory_io import read_kitti
from tests.helpers import (
    ROOM_SESSION_ARGS,
    assert_error_line,
    call_main,
    written_before_version_5,
)

# benchmarks/results/merge.md (the same split): combined ATE 0.48 cm; bound 3x that
COMBINED_ATE_BOUND_M = 0.015
MERGED_FILES = ("poses_slam.kitti.txt", "poses_slam.tum.txt", "sessions.csv", "loops.csv",
                "map.npz", "mesh.ply", "metrics.json")  # fmt: skip


@pytest.fixture()
def runs(room_sessions: dict[str, Path]) -> dict[str, Path]:
    return room_sessions


def _merge(*args: str):
    return call_main(merge_main, list(args))


def _run(*args: str):
    return call_main(run_main, list(args))


def _first_session_aligned_rmse(poses: np.ndarray, truth: np.ndarray, n: int) -> float:
    """RMSE of rows ``n:`` after aligning the truth on rows ``:n`` only (rigid, positions)."""
    from slam.algorithm.loops.place import _rigid_fit

    T = _rigid_fit(truth[:n, :3, 3], poses[:n, :3, 3], False)
    error = truth[n:, :3, 3] @ T[:3, :3].T + T[:3, 3] - poses[n:, :3, 3]
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))


def test_continuing_a_map_places_the_run_in_its_frame(runs):
    out = runs["continued"]
    for name in MERGED_FILES:
        assert (out / name).is_file(), name
    sessions = (out / "sessions.csv").read_text().splitlines()
    assert sessions[1].split(",")[1:] == [str(runs["a"]), "0", "60"]
    assert sessions[2].split(",")[1:] == [str(runs["b"]), "60", "60"]
    poses = read_kitti(out / "poses_slam.kitti.txt")
    first = read_kitti(runs["a"] / "poses_slam.kitti.txt")
    # the map's own session stays where it was (the joint graph only nudges it) ...
    assert np.abs(poses[:60, :3, 3] - first[:, :3, 3]).max() < COMBINED_ATE_BOUND_M
    # ... and the new one lands in its frame: truth aligned on the first session alone
    truth = read_kitti(out / "poses_gt.kitti.txt")
    assert _first_session_aligned_rmse(poses, truth, 60) < COMBINED_ATE_BOUND_M
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["inter_session_loops_kept"] >= 1
    assert metrics["combined_ate_rmse_m"] < COMBINED_ATE_BOUND_M
    session = json.loads((runs["b"] / "metrics.json").read_text())
    assert session["input"]["frames_total"] == 60
    assert "trajectory" in session and "mesh" not in session  # output.mesh_samples=0
    # ... which slam.eval scores afterwards, with the configuration's default samples
    scored = evaluate_run(runs["a"], make_plots=False, write=False)
    assert scored["mesh"]["num_samples"] == 100_000 and scored["mesh"]["accuracy_m"] < 0.05


def test_continuing_a_map_relocalises_live(runs):
    """The continuation was placed in the map while it ran: its own run folder's poses are
    already in the map's frame, where the final merge puts them."""
    session = json.loads((runs["b"] / "metrics.json").read_text())["relocalisation"]
    assert session["relocalised"], session
    assert session["submaps_tried"] >= 1
    assert session["scores"]["inlier_fraction"] >= 0.4
    live = read_kitti(runs["b"] / "poses_slam.kitti.txt")
    merged = read_kitti(runs["continued"] / "poses_slam.kitti.txt")[60:]
    assert np.abs(live[:, :3, 3] - merged[:, :3, 3]).max() < COMBINED_ATE_BOUND_M
    placed = f"submap {session['submap']} on the map's submap {session['map_submap']}"
    assert placed in (runs["continued"] / "run.log").read_text()


def test_two_sessions_merge_without_scans(runs, tmp_path: Path):
    out = runs["merged"]  # slam.merge a b, after every image was deleted
    for name in (*MERGED_FILES, "recording.rrd"):
        assert (out / name).is_file(), name
    poses = read_kitti(out / "poses_slam.kitti.txt")
    assert len(poses) == 120
    # merging afterwards gives what continuing the map gave
    np.testing.assert_allclose(poses, read_kitti(runs["continued"] / "poses_slam.kitti.txt"))
    sessions = (out / "sessions.csv").read_text().splitlines()
    assert sessions[1].split(",")[2:] == ["0", "60"] and sessions[2].split(",")[2:] == ["60", "60"]
    loops = (out / "loops.csv").read_text()
    assert "inter,0,1," in loops
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["inter_session_loops_kept"] >= 1
    ate = metrics["combined_ate_rmse_m"]
    assert ate < COMBINED_ATE_BOUND_M, f"combined ATE {ate:.4f} m"
    # the merged run is itself a session: it merges again with another run, and lists the
    # runs it joined; one of its own parts is refused (its frames would be there twice)
    again = _merge(str(out), str(runs["other"]), "--out", str(tmp_path / "again"), "--no-viz")
    assert again.returncode == 0, again.stderr
    rows = (tmp_path / "again" / "sessions.csv").read_text().splitlines()[1:]
    assert [row.split(",")[1:] for row in rows] == [
        [str(runs["a"]), "0", "60"],
        [str(runs["b"]), "60", "60"],
        [str(runs["other"]), "120", "10"],
    ]
    part = _merge(str(out), str(runs["b"]), "--out", str(tmp_path / "part"))
    assert_error_line(part, "same session", str(runs["b"]))
    assert not (tmp_path / "part").exists()


def test_run_merged_with_itself_is_refused(runs, tmp_path: Path):
    out = tmp_path / "self"
    result = _merge(str(runs["a"]), str(runs["a"]), "--out", str(out), "--no-viz")
    assert_error_line(result, "same session", str(runs["a"]))
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == []


def test_different_voxel_size_or_no_descriptors_is_refused(runs, tmp_path: Path):
    out = tmp_path / "out"
    result = _merge(str(runs["a"]), str(runs["coarse"]), "--out", str(out))
    assert_error_line(result, "voxel size", str(runs["coarse"]))
    assert not out.exists()
    # continuing it: refused before a frame is read (the data folder does not exist)
    data = tmp_path / "data"
    result = _run(
        "demo", "--root", str(data), "--no-viz", "--no-progress", "--out", str(out),
        "--map", str(runs["coarse"]), *ROOM_SESSION_ARGS,
    )  # fmt: skip
    assert_error_line(result, "voxel size", str(runs["coarse"]), "mapping.voxel_size_m=0.15")
    assert not out.exists() and not data.exists()
    result = _run(
        "demo", "--root", str(data), "--no-viz", "--no-progress", "--out", str(out),
        "--map", str(runs["a"]), "--set", "loop_closure.enabled=false", *ROOM_SESSION_ARGS,
    )  # fmt: skip
    assert_error_line(result, "loop closure is off", "loop_closure.enabled=true")
    assert not out.exists() and not data.exists()


def test_version_2_map_loads_but_is_not_merged(runs, tmp_path: Path):
    old = tmp_path / "old"
    old.mkdir()
    _, submaps = load_map(runs["b"] / "map.npz")
    written_before_version_5(runs["b"] / "map.npz", old / "map.npz", 2, submaps, session=False)
    assert load_map(old / "map.npz")[0].num_voxels > 0  # still a map
    result = _merge(str(runs["a"]), str(old), "--out", str(tmp_path / "out"))
    assert_error_line(result, "version 2", "re-run", "slam.run")


def test_runs_without_shared_place_are_reported(runs, tmp_path: Path):
    out = tmp_path / "out"
    result = _merge(str(runs["a"]), str(runs["other"]), "--out", str(out))
    assert_error_line(result, "shares no place", str(runs["other"]))
    assert not out.exists()


def test_bev_descriptor_recovers_a_planar_motion():
    """The LiDAR descriptor (bird's-eye ORB) matched across a known yaw and shift."""
    from slam.algorithm.loops.place import bev_descriptor, fit_matches, ratio_matches

    rng = np.random.default_rng(0)
    clouds = [rng.uniform([-40, -40, 0], [40, 40, 0.1], (20000, 3))]
    for _ in range(60):  # boxes standing on the ground
        centre, half = rng.uniform(-35, 35, 2), rng.uniform(0.5, 4, 2)
        xy = rng.uniform(centre - half, centre + half, (400, 2))
        clouds.append(np.column_stack([xy, rng.uniform(0, 3, 400)]))
    reference = np.concatenate(clouds)
    yaw, t = 0.3, np.array([3.0, -2.0, 0.0])
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    query = (reference - t) @ R  # reference = R query + t
    reference_places, query_places = bev_descriptor(reference, 0.5), bev_descriptor(query, 0.5)
    index = ratio_matches(reference_places, query_places)
    T, inliers = fit_matches(reference_places, query_places, index, inlier_m=1.0)
    assert T is not None and inliers >= 20
    assert np.linalg.norm(T[:3, 3] - t) < 0.2
    assert np.abs(T[:3, :3] - R).max() < 0.02


def _truth_and_guess(
    rotvec: list[float], t: list[float], yaw_off_rad: float, offset_m: list[float]
) -> tuple[np.ndarray, np.ndarray]:
    """A true pose and an initial guess off it by a yaw and a translation."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    guess = T.copy()
    guess[:3, :3] = Rotation.from_rotvec([0, 0, yaw_off_rad]).as_matrix() @ T[:3, :3]
    guess[:3, 3] += offset_m
    return T, guess


def _planes(rng, ghost: bool) -> tuple[np.ndarray, np.ndarray]:
    """A room corner with a box (points, normals); ``ghost`` adds a surface 5 cm above part of
    the floor, which the other side does not have, and a wall beyond the other's surfaces."""
    X, Y, Z = np.eye(3)
    O = np.zeros(3)
    specs = [(O, X, Y, Z, 2.0, 2.0), (O, Y, Z, X, 2.0, 1.0), (O, X, Z, Y, 2.0, 1.0),
             (np.array([1.2, 1.2, 0]), X, Z, -Y, 0.6, 0.5)]  # fmt: skip
    if ghost:
        specs += [(np.array([0.8, 0.2, 0.05]), X, Y, Z, 0.9, 0.9),
                  (np.array([2.5, 0.0, 0.0]), Y, Z, -X, 2.0, 1.0)]  # fmt: skip
    points, normals = [], []
    for origin, u, v, n, size_u, size_v in specs:
        a, b = (g.reshape(-1, 1) for g in np.meshgrid(np.arange(0, size_u, 0.03),
                                                      np.arange(0, size_v, 0.03)))  # fmt: skip
        points.append(origin + a * u + b * v + rng.normal(0, 0.002, (len(a), 3)))
        normals.append(np.tile(n, (len(a), 1)))
    return np.concatenate(points), np.concatenate(normals)


def test_merge_verification_is_not_pulled_by_surfaces_one_side_lacks():
    """Decoded surfaces of two sessions overlap only in part: the ICP's last gate is fine enough
    that a surface only one side has (5 cm off the other's) does not bias the edge, while the
    overlap that decides acceptance is measured at its own gate, whatever the ICP's gates."""

    from common.geometry import relative_motion
    from slam.algorithm.merge.config import MergeConfig
    from slam.algorithm.merge.surface import verify

    rng = np.random.default_rng(0)
    reference = _planes(rng, ghost=False)
    points, normals = _planes(rng, ghost=True)
    T, guess = _truth_and_guess([0.02, -0.03, 0.3], [0.3, -0.2, 0.05], 0.03, [0.05, -0.04, 0.06])
    R_inv = T[:3, :3].T
    query = ((points - T[:3, 3]) @ R_inv.T, normals @ R_inv.T)
    errors, overlaps = {}, {}
    coarse = MergeConfig(icp_gates_vu=(3.0, 1.5, 0.75))
    for name, cfg in (("default", MergeConfig()), ("coarse", coarse)):
        accepted, reason, T_found, scores, _ = verify(reference, query, guess, 0.1, cfg)
        assert accepted, reason
        errors[name] = relative_motion(T, T_found)
        overlaps[name] = scores["inlier_fraction"]
    assert errors["default"][0] < 0.002 and errors["default"][1] < 0.05
    assert errors["coarse"][0] > 3 * errors["default"][0]  # what a wide last gate costs
    assert 0.6 < overlaps["default"] < 0.95  # the extra wall overlaps nothing
    assert abs(overlaps["default"] - overlaps["coarse"]) < 0.02


def test_a_coarse_subset_brings_the_registration_where_all_points_take_it():
    """A localisation's registration aligns a subset of its points in the gates wider than half
    a voxel (``LocaliseConfig.coarse_query_points``): from a guess 15 cm and 3 deg off it ends
    where the registration of every point through every gate ends, with fewer KD-tree queries."""
    from scipy.spatial import cKDTree

    from common.geometry import relative_motion
    from slam.algorithm.merge.config import MergeConfig
    from slam.algorithm.merge.map_constraints import subsample
    from slam.algorithm.merge.surface import align_surfaces

    rng = np.random.default_rng(1)
    reference = _planes(rng, ghost=False)
    points, _ = _planes(rng, ghost=False)
    T, guess = _truth_and_guess([0.01, -0.02, 0.2], [0.3, -0.2, 0.05], 0.05, [0.1, -0.1, 0.05])
    query = subsample((points - T[:3, 3]) @ T[:3, :3], 2500)

    class CountingTree(cKDTree):
        queried = 0

        def query(self, x, *args, **kwargs):
            CountingTree.queried += len(x)
            return super().query(x, *args, **kwargs)

    found, queried = {}, {}
    for name, coarse in (("all", None), ("subset", subsample(query, 625))):
        CountingTree.queried = 0
        tree = CountingTree(reference[0])
        result = align_surfaces(reference, query, guess, 0.1, MergeConfig(), tree, coarse)
        found[name], queried[name] = result.T_ref_query, CountingTree.queried
    for T_found in found.values():
        error_m, error_deg = relative_motion(T, T_found)
        assert error_m < 0.003 and error_deg < 0.1
    assert relative_motion(found["all"], found["subset"])[0] < 0.001
    assert queried["subset"] < 0.7 * queried["all"]
