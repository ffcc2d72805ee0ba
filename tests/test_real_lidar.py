"""Real LiDAR scans from ../shared/data (MulRan Riverside02 keyframes, KITTI raw HDL-64E): PCD
reading, the configuration derived from the first scan, and a short mapping run with the
reference poses. Skipped when the data is absent (a user's machine does not have it)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from frontends.sources import make_source
from frontends.sources.pcd_folder import pcd_scan_files, read_pcd_points
from slam.assembly.config import default_config_path, load_run_config
from slam.assembly.lidar_scale import scale_config, scan_extent_m
from tests.helpers import call_main

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA = REPO_ROOT.parent / "shared" / "data"
MULRAN = DATA / "mulran_riverside02_keyframes"
KITTI_RAW = DATA / "kitti_raw_22"
E2E_FRAMES = 10

needs_mulran = pytest.mark.skipif(
    not (MULRAN / "scans").is_dir(), reason=f"MulRan keyframes not found at {MULRAN}"
)
needs_kitti_raw = pytest.mark.skipif(
    not KITTI_RAW.is_dir(), reason=f"KITTI raw scans not found at {KITTI_RAW}"
)
SETS = [
    pytest.param(MULRAN / "scans", marks=needs_mulran, id="mulran"),
    pytest.param(KITTI_RAW, marks=needs_kitti_raw, id="kitti_raw"),
]


def _header_points(path: Path) -> int:
    with path.open("rb") as f:
        for raw in f:
            line = raw.decode("ascii", errors="replace").split()
            if line and line[0] == "POINTS":
                return int(line[1])
    raise AssertionError(f"{path}: no POINTS line")


@pytest.mark.parametrize("folder", SETS)
def test_every_scan_has_the_points_its_header_says(folder: Path) -> None:
    files = pcd_scan_files(folder)
    assert len(files) == {"scans": 331, "kitti_raw_22": 22}[folder.name]
    for path in files:
        points = read_pcd_points(path)
        assert points.shape == (_header_points(path), 3), path
        assert np.isfinite(points).all(), path


@needs_mulran
def test_mulran_source_takes_times_txt_and_the_reference_poses() -> None:
    source = make_source(
        "lidar", root=MULRAN / "scans", gt_poses=MULRAN / "optimized_poses.txt", frames=slice(0, 3)
    )
    stamps = np.loadtxt(MULRAN / "times.txt")
    reference = np.loadtxt(MULRAN / "optimized_poses.txt")[:3].reshape(3, 3, 4)
    for i, frame in enumerate(source):
        assert frame.timestamp == pytest.approx(stamps[i], abs=1e-6)
        np.testing.assert_allclose(frame.T_W_S_gt[:3], reference[i], atol=1e-6)


@pytest.mark.parametrize("folder", SETS)
def test_config_derived_from_the_first_real_scan(folder: Path) -> None:
    """On real car LiDARs the derived settings land near configs/kitti.yaml (tuned by hand for
    an HDL-64E), ranges cover the scan, and the first scan is representative of the rest."""
    files = pcd_scan_files(folder)
    first = read_pcd_points(files[0])
    cfg = load_run_config(default_config_path("lidar"))
    scale_config(cfg, first)
    kitti = load_run_config(default_config_path("kitti"))
    extent, farthest = scan_extent_m(first)
    ranges = np.linalg.norm(first, axis=1)
    assert cfg.odometry.kiss_icp.data.max_range >= farthest
    assert np.mean(ranges <= cfg.submaps.max_range_m) >= 0.85
    assert 0.6 * kitti.mapping.voxel_size_m < cfg.mapping.voxel_size_m
    assert cfg.mapping.voxel_size_m < 1.6 * kitti.mapping.voxel_size_m
    assert cfg.submaps.map_voxel_m < cfg.submaps.loop_voxel_m < cfg.mapping.voxel_size_m
    # a loop needs travel beyond a submap's own length and reach within a scan's extent
    assert cfg.loop_closure.min_travel_m > cfg.submaps.max_distance_m
    assert cfg.loop_closure.lidar.proximity_radius_m < extent
    # the first scan's extent is typical of the recording (every 10th scan)
    others = [scan_extent_m(read_pcd_points(p))[0] for p in files[::10]]
    assert 0.7 * np.median(others) < extent < 1.4 * np.median(others)


@needs_mulran
def test_mulran_keyframes_per_submap() -> None:
    """A submap spans several keyframes (median 5.7 m apart) yet stays within the map range."""
    cfg = load_run_config(default_config_path("lidar"))
    scale_config(cfg, read_pcd_points(pcd_scan_files(MULRAN / "scans")[0]))
    poses = np.loadtxt(MULRAN / "optimized_poses.txt").reshape(-1, 3, 4)
    spacing = np.median(np.linalg.norm(np.diff(poses[:, :, 3], axis=0), axis=1))
    assert 3 * spacing < cfg.submaps.max_distance_m <= cfg.submaps.max_range_m


@needs_mulran
def test_mulran_mapping_with_reference_poses(tmp_path: Path) -> None:
    """10 keyframes with --odometry gt: the run folder is complete, the trajectory is the
    reference, and the mesh lies on the scan points (placed by the reference poses)."""
    import trimesh
    from scipy.spatial import cKDTree

    from slam.app.cli import main

    out = tmp_path / "run"
    command = [
        "lidar",
        str(MULRAN / "scans"),
        "--odometry",
        "gt",
        "--frames",
        f"0:{E2E_FRAMES}",
        "--set",
        f"source.lidar.gt_poses={MULRAN / 'optimized_poses.txt'}",
        "--no-viz",
        "--no-progress",
        "--out",
        str(out),
    ]
    done = call_main(main, command)  # in this process: the command line is not under test
    assert done.returncode == 0, done.stderr[-2000:]
    for name in ("config.yaml", "metrics.json", "mesh.ply", "map.npz", "poses_slam.kitti.txt"):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_frames"] == E2E_FRAMES
    assert metrics["trajectory"]["slam"]["ate_rmse_m"] < 0.01
    poses = np.loadtxt(out / "poses_slam.kitti.txt").reshape(-1, 3, 4)
    config = (out / "config.yaml").read_text()
    assert "scale_from_first_scan: true" in config
    points = []
    for path, pose in zip(pcd_scan_files(MULRAN / "scans")[:E2E_FRAMES], poses, strict=True):
        scan = read_pcd_points(path)  # the map takes points to 8/3 of the extent: all of them
        points.append(scan @ pose[:, :3].T + pose[:, 3])
    mesh = trimesh.load(out / "mesh.ply", process=False)
    assert len(mesh.faces) > 10_000
    distance, _ = cKDTree(np.concatenate(points)).query(np.asarray(mesh.vertices))
    # the map voxel is ~1 m; the surface passes within a fraction of it of the points
    assert np.median(distance) < 0.3
    assert np.mean(distance < 1.0) > 0.9
