"""Construct the parts of a run (source, odometry, neural map, logger) from a :class:`RunConfig`."""

from __future__ import annotations

from typing import Any

from frontends.odometry.base import Odometry, make_odometry
from frontends.sources.base import Source, make_source
from slam.assembly.config import ConfigError, RunConfig


def frame_slice(text: str | None) -> slice | None:
    """``"A:B[:STEP]"`` as a slice (validated by the runner), None for all frames."""
    if text is None:
        return None
    parts = [int(p) if p.strip() else None for p in text.split(":")]
    return slice(*parts)


def source_kwargs(cfg: RunConfig) -> dict[str, Any]:
    """Keyword arguments of ``make_source`` for the configured dataset."""
    src = cfg.source
    frames = frame_slice(src.frames)
    depth = src.depth.model_dump()
    if src.dataset == "generated":
        g = cfg.generated
        kwargs: dict[str, Any] = {
            "kind": g.kind,
            "root": src.root,
            "num_frames": g.num_frames,
            "seed": g.seed,
            "frames": frames,
        }
        if g.kind == "lidar":
            kwargs.update(
                trajectory=g.trajectory,
                kitti_poses=g.kitti_poses,
                kitti_calib=g.kitti_calib,
                start=g.start,
                step=g.step,
                azimuth_steps=g.azimuth_steps,
                terrain_relief_m=g.terrain_relief_m,
                street_style=g.street_style,
                range_noise_m=g.range_noise_m,
                dropout=g.dropout,
                loader_options={"max_range_m": src.kitti.max_range_m},
            )
        else:
            kwargs.update(width=g.width, height=g.height, loader_options={"depth_options": depth})
        return kwargs
    if src.dataset == "lidar":
        lidar = src.lidar
        return {
            "root": src.root,
            "dataloader": lidar.dataloader,
            "sequence": lidar.sequence,
            "topic": lidar.topic,
            "frames": frames,
            "gt_poses": lidar.gt_poses,
            "nominal_rate_hz": lidar.nominal_rate_hz,
            "max_range_m": lidar.max_range_m,
            "max_time_difference_s": src.tum.max_time_difference_s,
        }
    kwargs = {"root": src.root, "sequence": src.sequence, "frames": frames}
    if src.dataset == "kitti":
        kwargs.update(
            correct_vertical_angle=src.kitti.correct_vertical_angle,
            max_range_m=src.kitti.max_range_m,
        )
    elif src.dataset in ("tum", "icl"):
        kwargs.update(max_difference=src.tum.max_time_difference_s, depth_options=depth)
        if src.dataset == "tum":
            intrinsics = src.tum.intrinsics
            kwargs.update(
                intrinsics=None if intrinsics is None else intrinsics.model_dump(),
                depth_scale=src.tum.depth_scale,
                allow_outside_paths=src.tum.allow_outside_paths,
            )
    else:
        kwargs["depth_options"] = depth
    return kwargs


def build_source(cfg: RunConfig) -> Source:
    """The configured source (generates a generated sequence on first use)."""
    return make_source(cfg.source.dataset, **source_kwargs(cfg))


def odometry_method(cfg: RunConfig, sensor: str) -> str:
    """The odometry name, resolving ``auto`` by the sensor."""
    method = cfg.odometry.method
    if method == "auto":
        return "kiss-icp" if sensor == "lidar" else "rgbd"
    return method


def _kiss_icp(cfg: RunConfig) -> Odometry:
    """KISS-ICP, in a child process where that lets the worker threads run meanwhile."""
    from frontends.odometry.child_process import ChildProcessOdometry, child_process_available

    options = {"config": cfg.odometry.kiss_icp, "start_scans": cfg.odometry.kiss_icp_start_scans}
    if cfg.odometry.child_process and cfg.map_worker and child_process_available():
        return ChildProcessOdometry(
            "kiss-icp", reply_timeout_s=cfg.odometry.child_reply_timeout_s, **options
        )
    return make_odometry("kiss-icp", **options)


def build_odometry(cfg: RunConfig, sensor: str) -> Odometry:
    method = odometry_method(cfg, sensor)
    if method == "kiss-icp":
        return _kiss_icp(cfg)
    if method == "rgbd":
        return make_odometry(method, config=cfg.odometry.rgbd)
    return make_odometry(method)


def build_map(cfg: RunConfig):
    """An empty neural map with the shipped prior (or ``mapping.weights_path``)."""
    from mapping.config import resolve_device
    from mapping.neural_map import NeuralMap

    try:
        resolve_device(cfg.mapping.device)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    return NeuralMap(cfg.mapping)
