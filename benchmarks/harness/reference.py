"""The reference systems the benchmarks compare against: KISS-ICP alone, KISS-SLAM (in its own
environment) and OpenCV's HashTSDF.

KISS-SLAM's environment is found through one setting: ``$BENCH_KISS_SLAM_VENV``, by default
``.venv-kiss-slam`` in the repository (``make kiss-slam-env`` creates it). Where it is missing
or broken, :func:`kiss_slam` returns ``{"skipped": <reason>}`` instead of failing.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.harness.child import run_command
from benchmarks.harness.kitti import kitti_root
from benchmarks.harness.paths import REPO, WORK_DIR

KISS_SLAM_ENV_LOG = WORK_DIR / "kiss-slam-env.log"


def kiss_slam_venv() -> Path:
    """The KISS-SLAM environment: ``$BENCH_KISS_SLAM_VENV`` or ``<repo>/.venv-kiss-slam``."""
    return Path(os.environ.get("BENCH_KISS_SLAM_VENV") or REPO / ".venv-kiss-slam")


def kiss_slam_unavailable() -> str | None:
    """Why KISS-SLAM cannot run here, or None when it can."""
    venv = kiss_slam_venv()
    if not (venv / "bin" / "kiss_slam_pipeline").is_file():
        reason = f"no KISS-SLAM environment at {venv} (`make kiss-slam-env` creates it"
        if KISS_SLAM_ENV_LOG.is_file():
            lines = KISS_SLAM_ENV_LOG.read_text(errors="replace").strip().splitlines()
            reason += f"; its last attempt said: {(lines or ['?'])[-1][:200]}"
        return reason + ")"
    return None


def kiss_icp_alone(source, kiss_config) -> dict[str, Any]:
    """KISS-ICP's ``register_frame`` on every frame of ``source``: speed and trajectory error."""
    from kiss_icp.kiss_icp import KissICP

    from slam.evaluation.metrics.trajectory import ate_per_axis_rmse, ate_rmse

    kiss = KissICP(kiss_config)
    poses = []
    start, cpu_start = time.perf_counter(), time.process_time()
    for frame in source:
        kiss.register_frame(np.asarray(frame.points, dtype=np.float64), np.zeros(0))
        poses.append(np.array(kiss.last_pose))
    wall = time.perf_counter() - start
    poses = np.array(poses)
    return {
        "frames": len(poses),
        "wall_s": wall,
        "cpu_s": time.process_time() - cpu_start,
        "fps": len(poses) / wall,
        "ate_odometry_m": ate_rmse(poses, source.gt_poses),
        "ate_xyz_odometry_m": ate_per_axis_rmse(poses, source.gt_poses).tolist(),
    }


def _reported(output: str, label: str) -> float | None:
    """A number KISS-SLAM prints after ``label`` in its summary."""
    for line in output.splitlines():
        if label in line:
            try:
                return float(line.replace(label, "").split()[0].strip("|"))
            except (IndexError, ValueError):
                return None
    return None


def _kiss_slam_input(source) -> tuple[list[str], np.ndarray | None]:
    """KISS-SLAM's data arguments for a generated KITTI-layout source, reading the scans as ours
    does, and the ``Tr`` that its poses file is expressed with (None: the LiDAR frame).

    Its ``kitti`` dataloader applies KISS-ICP's 0.205 deg KITTI correction and writes camera-frame
    poses (``Tr @ T @ inv(Tr)``). It is used only where our loader applies the correction too;
    otherwise the ``generic`` dataloader reads the same ``.bin`` files untouched, in the LiDAR
    frame, so both systems get the same points.
    """
    from frontends.sources.kitti import KittiSource

    inner = source.inner
    if isinstance(inner, KittiSource) and inner.correct_vertical_angle:
        args = [str(kitti_root(source)), "--dataloader", "kitti", "--sequence", "00"]
        return args, inner.T_cam_lidar
    return [str(Path(source.sequence_dir) / "velodyne"), "--dataloader", "generic"], None


def kiss_slam(source, num_frames: int | None = None) -> dict[str, Any]:
    """KISS-SLAM's ``kiss_slam_pipeline`` (default config) on a generated KITTI-layout source, as
    its own measured process; ``{"skipped": reason}`` when it cannot run."""
    reason = kiss_slam_unavailable()
    if reason is not None:
        return {"skipped": reason}
    from slam.evaluation.metrics.trajectory import ate_per_axis_rmse, ate_rmse
    from slam.run_folder.trajectory_io import read_kitti

    data_args, T_cam_lidar = _kiss_slam_input(source)
    command = [
        str(kiss_slam_venv() / "bin" / "kiss_slam_pipeline"),
        *data_args,
        *(["--n-scans", str(num_frames)] if num_frames else []),
    ]
    with tempfile.TemporaryDirectory(prefix="kiss-slam-") as work:
        run = run_command(command, cwd=Path(work))
        if run.returncode != 0:
            said = (run.stdout.strip().splitlines() or ["?"])[-1]
            return {"skipped": f"KISS-SLAM exited with {run.returncode}: {said[:200]}"}
        found = sorted(Path(work).rglob("*_poses_kitti.txt"))
        if not found:
            return {"skipped": "KISS-SLAM wrote no poses file"}
        poses = read_kitti(found[0])
    if T_cam_lidar is not None:
        poses = np.linalg.inv(T_cam_lidar) @ poses @ T_cam_lidar
    gt = source.gt_poses[: len(poses)]
    usage = run.usage
    return {
        "frames": len(poses),
        "wall_s": usage.wall_s,
        "cpu_s": usage.cpu_s,
        "fps": len(poses) / usage.wall_s,
        "peak_rss_mb": usage.peak_rss_mb,
        "ate_slam_m": ate_rmse(poses, gt),
        "ate_xyz_slam_m": ate_per_axis_rmse(poses, gt).tolist(),
        "closures": _reported(run.stdout, "Number of closures found"),
        "own_frequency_hz": _reported(run.stdout, "Average Frequency"),
    }


def tsdf(frames: list, voxel_m: float, max_points: int):
    """OpenCV HashTSDF integration of RGB-D ``frames`` at their ``T_W_S_gt``; the surface is
    ray-cast from every input pose (world frame, at most ``max_points`` points). Returns
    (points, estimated memory in bytes, integration s, ray-casting s)."""
    import cv2

    intr = frames[0].intrinsics
    settings = cv2.VolumeSettings(cv2.VolumeType_HashTSDF)
    settings.setVoxelSize(voxel_m)
    settings.setTsdfTruncateDistance(4 * voxel_m)
    settings.setDepthFactor(1.0)
    settings.setMaxDepth(10.0)
    for setter in ("Integrate", "Raycast"):
        getattr(settings, f"set{setter}Width")(intr.width)
        getattr(settings, f"set{setter}Height")(intr.height)
        getattr(settings, f"setCamera{setter}Intrinsics")(intr.K.astype(np.float32))
    volume = cv2.Volume(cv2.VolumeType_HashTSDF, settings)
    t0 = time.perf_counter()
    for frame in frames:
        volume.integrate(frame.depth.astype(np.float32), frame.T_W_S_gt.astype(np.float32))
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    per_frame = max(1, max_points // len(frames))
    rng = np.random.default_rng(0)
    clouds = []
    for frame in frames:
        pts, _ = volume.raycast(frame.T_W_S_gt.astype(np.float32))
        P = np.asarray(pts).reshape(-1, 4)[:, :3].astype(np.float64)
        P = P[np.isfinite(P).all(1) & (np.abs(P).sum(1) > 0)]
        if len(P) > per_frame:
            P = P[rng.choice(len(P), per_frame, replace=False)]
        T = frame.T_W_S_gt
        clouds.append(P @ T[:3, :3].T + T[:3, 3])
    points = np.concatenate(clouds)
    return points, _tsdf_memory(frames, voxel_m), build, time.perf_counter() - t0


def _tsdf_memory(frames: list, voxel_m: float) -> int:
    """Estimated HashTSDF memory: 16^3-voxel units touched by the depth points +- truncation
    along their rays, times 16^3 voxels of 2 bytes (int8 TSDF + uint8 weight)."""
    unit = 16 * voxel_m
    keys = set()
    for frame in frames:
        T = frame.T_W_S_gt
        P = frame.points[:: max(1, len(frame.points) // 20000)]
        rays = P / np.linalg.norm(P, axis=1, keepdims=True)
        for offset in np.linspace(-4 * voxel_m, 4 * voxel_m, 5):
            Q = (P + offset * rays) @ T[:3, :3].T + T[:3, 3]
            keys.update(map(tuple, np.floor(Q / unit).astype(np.int64)))
    return len(keys) * 16**3 * 2
