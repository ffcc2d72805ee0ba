"""Generate whole sequences on disk: a LiDAR sequence in KITTI layout, an RGB-D one in TUM layout.

Both write into a hidden temporary folder next to the target and move the finished result into
place at the end, so an interrupted generation never leaves a sequence that looks complete.
Everything random is drawn from generators seeded by ``seed`` (and the frame index), so the same
arguments give byte-identical files.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Literal

import numpy as np

from frontends.errors import DatasetError
from frontends.generate import writers
from frontends.generate.camera import RgbdCameraConfig, render_rgbd, unit_pixel_rays
from frontends.generate.lidar import LidarConfig, beam_directions, simulate_scan
from frontends.generate.raycast import Raycaster
from frontends.generate.scene import Scene, room_scene
from frontends.generate.street import StreetStyle, street_scene
from frontends.generate.texture import face_table
from frontends.generate.trajectories import (
    kitti_lidar_trajectory,
    loop_lidar_trajectory,
    room_camera_trajectory,
)

log = logging.getLogger(__name__)

LIDAR_RATE_HZ = 10.0
CAMERA_RATE_HZ = 30.0


@contextmanager
def _staging_dir(parent: Path, prefix: str) -> Iterator[Path]:
    """A hidden temporary folder in ``parent`` that is removed unless its content was moved."""
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{prefix}-", dir=parent))
    try:
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _replace_dir(src: Path, dst: Path, overwrite: bool) -> None:
    if dst.exists():
        if not overwrite:
            raise DatasetError(f"{dst}: already exists; remove it or pass overwrite=True")
        shutil.rmtree(dst)
    os.replace(src, dst)


class _LidarJob:
    """Renders and writes scan ``i`` at pose ``T_scene_S``; returns its number of points."""

    def __init__(self, scene: Scene, config: LidarConfig, seed: int, out_dir: Path) -> None:
        self.scene, self.config, self.seed, self.out_dir = scene, config, seed, out_dir
        self._raycaster: Raycaster | None = None

    def __call__(self, i: int, T_scene_S: np.ndarray) -> int:
        if self._raycaster is None:
            self._raycaster = Raycaster(self.scene.mesh)
            self._directions = beam_directions(self.config)
        rng = np.random.default_rng([self.seed, i, 1])
        points, reflectance = simulate_scan(
            self._raycaster, self.scene, T_scene_S, self.config, rng, self._directions
        )
        writers.write_velodyne_bin(self.out_dir / f"{i:06d}.bin", points, reflectance)
        return len(points)


class _RgbdJob:
    """Renders and writes RGB-D frame ``i`` for ``(stamp, T_W_C)``; returns its valid pixels."""

    def __init__(self, scene: Scene, config: RgbdCameraConfig, seed: int, out_dir: Path) -> None:
        self.scene, self.config, self.seed, self.out_dir = scene, config, seed, out_dir
        self._raycaster: Raycaster | None = None

    def __call__(self, i: int, item: tuple[str, np.ndarray]) -> int:
        if self._raycaster is None:
            self._raycaster = Raycaster(self.scene.mesh)
            self._rays = unit_pixel_rays(self.config.intrinsics)
            self._table = face_table(self.scene)
        stamp, T_W_C = item
        rng = np.random.default_rng([self.seed, i, 2])
        depth, rgb = render_rgbd(
            self._raycaster,
            self.scene,
            T_W_C,
            self.config,
            rng,
            seed=self.seed,
            unit_rays_C=self._rays,
            table=self._table,
        )
        writers.write_png(self.out_dir / "rgb" / f"{stamp}.png", rgb)
        writers.write_png(self.out_dir / "depth" / f"{stamp}.png", depth)
        return int(np.count_nonzero(depth))


_JOB = None


def _init_worker(job) -> None:
    global _JOB
    _JOB = job


def _call_worker(args: tuple[int, object]) -> int:
    return _JOB(*args)


def _run_frames(job, items: list, workers: int | None) -> list[int]:
    """``job(i, item)`` for every item, in this process or a pool of ``workers`` processes."""
    if workers is None:
        workers = min(2, os.cpu_count() or 1)
    workers = max(1, min(workers, len(items)))
    if workers == 1:
        return [job(i, item) for i, item in enumerate(items)]
    import multiprocessing

    context = multiprocessing.get_context("fork" if os.name == "posix" else "spawn")
    pool = context.Pool(workers, initializer=_init_worker, initargs=(job,))
    try:
        counts = pool.map(_call_worker, list(enumerate(items)), chunksize=4)
        # each worker leaves on its end-of-work message; leaving the pool with ``with`` would
        # end them by SIGTERM, which a Python handler they inherited (Ray's driver installs
        # one) can catch or lose, leaving the pool's join waiting for ever
        pool.close()
        pool.join()
        return counts
    finally:
        pool.terminate()  # after a failure; a no-op once joined


def generate_lidar_sequence(
    root: Path,
    *,
    sequence: str = "00",
    num_frames: int,
    trajectory: Literal["loop", "kitti"] = "loop",
    kitti_poses: Path | None = None,
    kitti_calib: Path | None = None,
    start: int = 0,
    step: int = 1,
    seed: int = 0,
    azimuth_steps: int = 2048,
    lidar: LidarConfig | None = None,
    terrain_relief_m: float = 0.0,
    street_style: StreetStyle = "standard",
    overwrite: bool = False,
    workers: int | None = None,
) -> Path:
    """Simulate a 64-beam LiDAR driving through a street and write it in KITTI odometry layout.

    Writes ``root/sequences/<sequence>/{velodyne/NNNNNN.bin, calib.txt, times.txt, gt_mesh.ply}``
    and ``root/poses/<sequence>.txt`` (left-camera poses, as KITTI). The LiDAR ground truth a
    KITTI loader recovers with ``inv(Tr) @ T_cam @ Tr`` starts at the identity; ``gt_mesh.ply`` is
    in that same world frame.

    Args:
        root: KITTI dataset root (created if missing).
        sequence: two-digit sequence name.
        num_frames: number of scans.
        trajectory: ``"loop"`` (one lap around a block, ~1 m/frame at ~186 frames) or ``"kitti"``
            (frames ``start, start+step, ...`` of a real KITTI ground-truth trajectory).
        kitti_poses: KITTI ``poses/NN.txt`` (needed for ``trajectory="kitti"``).
        kitti_calib: its ``sequences/NN/calib.txt`` (for ``Tr``).
        start, step: window of the KITTI trajectory.
        seed: seed of the scene and the sensor noise.
        azimuth_steps: firings per revolution (2048 ~ HDL-64E); ignored when ``lidar`` is given.
        lidar: full scanner configuration.
        terrain_relief_m: height of the hills that rise away from the road (0: the ground beside
            the road continues the road's height; the road itself always follows the
            trajectory's elevation, e.g. the real KITTI profile).
        street_style: layout of the street (``standard``, ``sparse`` or ``periodic``; see
            :func:`frontends.generate.street.street_scene`).
        overwrite: replace an existing sequence of the same name.
        workers: processes rendering frames (default: up to 2, one per CPU); the output does
            not depend on it.

    Returns:
        The sequence folder ``root/sequences/<sequence>``.
    """
    t_start = time.perf_counter()
    root = Path(root)
    target = root / "sequences" / sequence
    if target.exists() and not overwrite:
        raise DatasetError(f"{target}: already exists; remove it or pass overwrite=True")
    config = lidar or LidarConfig(azimuth_steps=azimuth_steps)
    if trajectory == "loop":
        T_scene_S = loop_lidar_trajectory(num_frames)
        closed = True
        frame_gap = 1
    elif trajectory == "kitti":
        if kitti_poses is None or kitti_calib is None:
            raise DatasetError(
                "trajectory='kitti' needs kitti_poses=<poses/NN.txt> and kitti_calib=<calib.txt>"
            )
        T_scene_S = kitti_lidar_trajectory(
            kitti_poses, kitti_calib, start=start, num_frames=num_frames, step=step
        )
        closed = False
        frame_gap = step
    else:
        raise DatasetError(f"unknown trajectory '{trajectory}'; choose 'loop' or 'kitti'")

    path_xyz = T_scene_S[:, :3, 3]
    if closed:
        path_xyz = np.vstack([path_xyz, path_xyz[:1]])
    scene = street_scene(path_xyz, seed=seed, relief_m=terrain_relief_m, style=street_style)
    T_W_scene = np.linalg.inv(T_scene_S[0])
    T_W_S = T_W_scene @ T_scene_S
    T_W_S[0] = np.eye(4)
    T_cam = writers.T_CAM_LIDAR @ T_W_S @ np.linalg.inv(writers.T_CAM_LIDAR)

    with _staging_dir(root, f"generating-{sequence}") as tmp:
        seq_dir = tmp / "sequences" / sequence
        (seq_dir / "velodyne").mkdir(parents=True)
        (tmp / "poses").mkdir()
        counts = _run_frames(
            _LidarJob(scene, config, seed, seq_dir / "velodyne"), list(T_scene_S), workers
        )
        total_points = sum(counts)
        writers.write_kitti_calib(seq_dir / "calib.txt")
        writers.write_kitti_times(
            seq_dir / "times.txt", np.arange(num_frames) * frame_gap / LIDAR_RATE_HZ
        )
        writers.write_kitti_poses(tmp / "poses" / f"{sequence}.txt", T_cam)
        writers.write_mesh_ply(seq_dir / "gt_mesh.ply", scene.transformed(T_W_scene).mesh)

        (root / "poses").mkdir(exist_ok=True)
        (root / "sequences").mkdir(exist_ok=True)
        os.replace(tmp / "poses" / f"{sequence}.txt", root / "poses" / f"{sequence}.txt")
        _replace_dir(seq_dir, target, overwrite)
    log.info(
        "generated %d scans (%.0f points each) in %s in %.1f s",
        num_frames,
        total_points / num_frames,
        target,
        time.perf_counter() - t_start,
    )
    return target


def generate_rgbd_sequence(
    root: Path,
    *,
    num_frames: int,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    camera: RgbdCameraConfig | None = None,
    overwrite: bool = False,
    workers: int | None = None,
) -> Path:
    """Simulate an RGB-D camera circling a textured room and write it in TUM RGB-D layout.

    Writes ``root/{rgb/<t>.png, depth/<t>.png, rgb.txt, depth.txt, associations.txt,
    groundtruth.txt, gt_mesh.ply, intrinsics.txt}``; depth PNGs are uint16 metres * 5000 (0 =
    invalid); ground truth is camera-to-world (x right, y down, z forward) in the room frame of
    ``gt_mesh.ply``; ``intrinsics.txt`` holds 'fx fy cx cy width height depth_scale'.

    Args:
        root: the sequence folder to create.
        num_frames: number of frames (one lap of the room; 30 Hz timestamps).
        seed: seed of the room colours/layout and the sensor noise.
        width, height: image size (intrinsics scale with it); ignored when ``camera`` is given.
        camera: full camera configuration.
        overwrite: replace an existing folder.
        workers: processes rendering frames (default: up to 2, one per CPU); the output does
            not depend on it.

    Returns:
        ``root``.
    """
    t_start = time.perf_counter()
    root = Path(root)
    if root.exists() and not overwrite:
        raise DatasetError(f"{root}: already exists; remove it or pass overwrite=True")
    config = camera or RgbdCameraConfig(width=width, height=height)
    scene = room_scene(seed=seed)
    poses = room_camera_trajectory(num_frames)
    stamps = [
        writers.tum_stamp(writers.TUM_START_TIME_S + i / CAMERA_RATE_HZ) for i in range(num_frames)
    ]

    with _staging_dir(root.parent, f"generating-{root.name}") as tmp:
        (tmp / "rgb").mkdir()
        (tmp / "depth").mkdir()
        _run_frames(
            _RgbdJob(scene, config, seed, tmp), list(zip(stamps, poses, strict=True)), workers
        )
        writers.write_tum_lists(tmp, stamps)
        writers.write_tum_groundtruth(tmp / "groundtruth.txt", stamps, poses)
        writers.write_intrinsics(
            tmp / writers.INTRINSICS_FILE, config.intrinsics, config.depth_scale
        )
        writers.write_mesh_ply(tmp / "gt_mesh.ply", scene.mesh)
        _replace_dir(tmp, root, overwrite)
    log.info(
        "generated %d RGB-D frames in %s in %.1f s", num_frames, root, time.perf_counter() - t_start
    )
    return root
