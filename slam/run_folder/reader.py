"""A run folder as :mod:`slam.evaluation.cli` reads it: the trajectories the run wrote, whether
the run finished, its saved map's voxels, and where its ground truth comes from."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from frontends.errors import DatasetError
from frontends.frame import Intrinsics
from mapping.map_io import load_map

logger = logging.getLogger("slam.eval")

TUM_MAX_DT_S = 0.02


class EvalError(ValueError):
    """A run folder or ground-truth file that cannot be evaluated (one-line message)."""


@dataclass
class RunTrajectories:
    """The poses a run wrote: ``timestamps`` (N,), ``odometry`` and ``slam`` (N, 4, 4);
    ``odometry`` is None for a merged run (``slam.merge``, ``--map``), which has none of its own."""

    timestamps: np.ndarray
    odometry: np.ndarray | None
    slam: np.ndarray


MERGED_RUN_FILE = "sessions.csv"
"""Written by ``slam.merge`` and ``slam.run --map`` only: marks a merged run folder."""


def is_merged_run(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds a merged run (its sessions' poses, no odometry of its own)."""
    return (Path(run_dir) / MERGED_RUN_FILE).is_file()


@dataclass
class GroundTruth:
    """Ground truth of a run, each part optional, with where it came from."""

    poses: np.ndarray | None = None
    poses_from: str = ""
    mesh_path: Path | None = None
    intrinsics: Intrinsics | None = None
    sensor: str | None = None


def read_run_trajectories(run_dir: Path) -> RunTrajectories:
    """Both trajectories of a run folder (TUM files carry the timestamps)."""
    from slam.run_folder.trajectory_io import read_kitti, read_tum

    run_dir = Path(run_dir)
    merged = is_merged_run(run_dir)
    if (run_dir / "poses_slam.tum.txt").is_file():  # a malformed one is reported, not skipped
        timestamps, slam = read_tum(run_dir / "poses_slam.tum.txt")
        odometry = None if merged else read_tum(run_dir / "poses_odometry.tum.txt")[1]
    else:
        slam = read_kitti(run_dir / "poses_slam.kitti.txt")
        odometry = None if merged else read_kitti(run_dir / "poses_odometry.kitti.txt")
        timestamps = np.arange(len(slam), dtype=np.float64)
    if odometry is not None and len(odometry) != len(slam):
        raise EvalError(
            f"{run_dir}: poses_odometry has {len(odometry)} poses but poses_slam {len(slam)}; "
            "the run was interrupted, re-run it"
        )
    return RunTrajectories(timestamps, odometry, slam)


def check_run_finished(run_dir: Path) -> None:
    """Raise :class:`EvalError` when the run's status file says it did not finish.

    A run folder without a status file (written before it existed) is taken as finished.
    """
    from slam.run_folder.outputs import RUN_STATUS_FILE, read_run_status

    status = read_run_status(Path(run_dir))
    if status is None or status.get("state") == "finished":
        return
    done, total = status.get("frames_done"), status.get("frames_total")
    where = f" at frame {done} of {total}" if done is not None and total is not None else ""
    state = status.get("state")
    if state == "running":
        what = f"did not finish (killed{where}, or still running)"
    else:
        what = f"was {state}{where}"
        if status.get("reason"):
            what += f" ({status['reason']})"
    raise EvalError(
        f"{Path(run_dir) / RUN_STATUS_FILE}: the run {what}; its outputs are partial, re-run it"
    )


def read_gt_poses(path: Path, timestamps: np.ndarray, num_frames: int) -> np.ndarray:
    """Ground-truth poses for the run's frames from a KITTI (one per frame) or TUM file.

    TUM poses are associated with the run's timestamps (nearest within 20 ms); frames without one
    get a row of NaN (they are not scored), and at least two frames need one.
    """
    from slam.run_folder.trajectory_io import read_kitti, read_tum

    path = Path(path)
    try:
        stamps, poses = read_tum(path)
    except DatasetError:
        poses = read_kitti(path)
        if len(poses) != num_frames:
            raise EvalError(
                f"{path}: {len(poses)} KITTI poses for a run of {num_frames} frames; pass the "
                "ground truth of exactly the frames the run used"
            ) from None
        return poses
    order = np.argsort(stamps)
    stamps, poses = stamps[order], poses[order]
    right = np.clip(np.searchsorted(stamps, timestamps), 1, len(stamps) - 1)
    left = right - 1
    nearest = np.where(
        np.abs(stamps[left] - timestamps) <= np.abs(stamps[right] - timestamps), left, right
    )
    nearest = np.where(len(stamps) == 1, 0, nearest)
    gap = np.abs(stamps[nearest] - timestamps)
    missing = gap > TUM_MAX_DT_S
    if np.count_nonzero(~missing) < 2:
        first = int(np.argmax(missing))
        raise EvalError(
            f"{path}: no ground-truth pose within {TUM_MAX_DT_S * 1e3:.0f} ms of frame {first} "
            f"(t = {timestamps[first]:.6f}); pass the ground truth of this sequence"
        )
    if missing.any():
        logger.warning("%s: %d frames have no ground-truth pose; not scored", path, missing.sum())
    out = poses[nearest].copy()
    out[missing] = np.nan
    return out


def _load_run_config(run_dir: Path):
    from slam.assembly.config import load_run_config

    path = Path(run_dir) / "config.yaml"
    return load_run_config(path) if path.is_file() else None


def _to_loader_frame(cfg, poses: np.ndarray) -> np.ndarray:
    """Poses in the dataset's frame (as files hold them) -> the loader's frame (mesh, map, source
    ground truth). The conversion is a reflection ``M T M``, its own inverse."""
    if cfg is None:
        return poses
    from frontends.sources import source_class

    try:
        cls = source_class(cfg.source.dataset)
    except DatasetError:
        return poses
    return cls.to_dataset_frame(poses)


def _source_ground_truth(cfg) -> GroundTruth:
    """Rebuild the run's source from its config (generated data may be regenerated)."""
    from slam.assembly.builders import build_source

    source = build_source(cfg)
    intrinsics = source[0].intrinsics if len(source) else None
    return GroundTruth(
        poses=source.gt_poses,
        poses_from=f"source {cfg.source.dataset} ({source.name})",
        mesh_path=source.gt_mesh_path,
        intrinsics=intrinsics,
        sensor=source.sensor,
    )


def find_ground_truth(
    run_dir: Path,
    trajectories: RunTrajectories,
    run_metrics: dict[str, Any],
    cfg,
    *,
    gt_poses_path: Path | None = None,
    gt_mesh_path: Path | None = None,
) -> GroundTruth:
    """Locate the ground truth of a run (order in the module docstring)."""
    run_dir = Path(run_dir)
    n = len(trajectories.slam)
    gt = GroundTruth(sensor=run_metrics.get("sensor"))
    if gt_poses_path is not None:
        gt.poses = read_gt_poses(gt_poses_path, trajectories.timestamps, n)
        gt.poses_from = str(gt_poses_path)
    else:
        for name in ("poses_gt.tum.txt", "poses_gt.kitti.txt"):
            if (run_dir / name).is_file():
                gt.poses = read_gt_poses(run_dir / name, trajectories.timestamps, n)
                gt.poses_from = str(run_dir / name)
                break
    if gt.poses is not None:
        gt.poses = _to_loader_frame(cfg, gt.poses)
    recorded_mesh = (run_metrics.get("mesh") or {}).get("gt_mesh")
    if gt_mesh_path is not None:
        gt.mesh_path = Path(gt_mesh_path)
    elif recorded_mesh and Path(recorded_mesh).is_file():
        gt.mesh_path = Path(recorded_mesh)
    needs_source = gt.poses is None or gt.mesh_path is None or gt.sensor == "rgbd"
    if needs_source and cfg is not None:
        try:
            from_source = _source_ground_truth(cfg)
        except (DatasetError, FileNotFoundError, OSError) as exc:
            logger.warning("could not rebuild the run's source for ground truth: %s", exc)
        else:
            if gt.poses is None and from_source.poses is not None:
                if len(from_source.poses) != n:
                    logger.warning(
                        "source has %d ground-truth poses for %d run frames; ignored",
                        len(from_source.poses),
                        n,
                    )
                else:
                    gt.poses, gt.poses_from = from_source.poses, from_source.poses_from
            gt.mesh_path = gt.mesh_path or from_source.mesh_path
            gt.intrinsics = from_source.intrinsics
            gt.sensor = gt.sensor or from_source.sensor
    return gt


def load_map_voxels(run_dir: Path) -> tuple[np.ndarray, float, dict[int, np.ndarray]]:
    """Voxel centres (world W), voxel size and current anchor poses ``T_W_A`` by submap id of the
    run's saved map."""

    candidates = sorted(Path(run_dir).glob("map.*"))
    if not candidates:
        raise EvalError(f"{run_dir}: no map file (map.npz); the run was made with write_map off")
    # voxel positions do not depend on the prior: read with the shipped one, whatever the file
    # was made with (its header never chooses a file to open)
    neural_map, submaps = load_map(candidates[0], check_model=False)
    centers, weights = neural_map.voxel_centers()
    anchors = {s.submap_id: np.asarray(s.T_W_A) for s in submaps}
    return np.asarray(centers)[np.asarray(weights) > 0], neural_map.voxel_size_m, anchors
