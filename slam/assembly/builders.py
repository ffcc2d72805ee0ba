"""Construct the parts of a run (source, odometry, neural map, logger) from a :class:`RunConfig`."""

from __future__ import annotations

from frontends.odometry.base import Odometry, make_odometry
from frontends.sources import Source, make_source
from slam.assembly.config import ConfigError, RunConfig
from slam.assembly.datasets import source_kwargs


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
