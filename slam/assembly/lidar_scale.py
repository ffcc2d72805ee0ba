"""Sensor-agnostic LiDAR settings: ranges, submap length and voxel sizes from the first scan.

A 16-beam indoor scanner and a 128-beam car LiDAR need settings an order of magnitude apart.
``configs/lidar.yaml`` leaves the scale-dependent fields unset and turns on
``source.lidar.scale_from_first_scan``; :func:`scale_config` then sets every such field that the
config files and ``--set`` left unset from the extent ``R`` of the first scan (the 90th
percentile of its point ranges). The factors reproduce the hand-tuned KITTI settings
(``configs/kitti.yaml``) for ``R`` of about 30 m:

=====================================================  =======================
field                                                  value
=====================================================  =======================
odometry.kiss_icp.data.max_range                       max point range (>= 2 R)
submaps.max_range_m (the map's points)                 8 R / 3
submaps.loop_max_range_m, submaps.max_distance_m       R
submaps.localise_scan_spacing_m                        R / 10
mapping.voxel_size_m                                   R / 30
submaps.map_voxel_m                                    voxel / 3
submaps.loop_voxel_m, overlap and inlier distances     voxel / 2
submaps.normal_radius_m                                1.5 voxel
loop_closure.min_travel_m                              3 R
loop_closure.lidar.proximity_radius_m                  0.7 R
loop_closure.lidar.icp_max_correspondence_m            1.5 voxel
pose_graph.gravity.voxel_m, normal_radius_m            voxel / 4, voxel
pose_graph.gravity.min_range_m, max_range_m            R / 15, 5 R / 3
=====================================================  =======================
"""

from __future__ import annotations

import logging

import numpy as np
from pydantic import BaseModel

from slam.assembly.config import RunConfig

logger = logging.getLogger(__name__)

EXTENT_PERCENTILE = 90.0
MAP_RANGE_FACTOR = 8.0 / 3.0
"""The map takes points to this multiple of the extent (80 m for an HDL-64E's 30 m), loop
closure to the extent itself (configs/kitti.yaml; benchmarks/bench_lidar_map.py)."""


def scan_extent_m(points: np.ndarray) -> tuple[float, float]:
    """(90th percentile, maximum) of the point ranges of a scan, in metres."""
    ranges = np.linalg.norm(np.asarray(points, dtype=np.float64), axis=1)
    ranges = ranges[np.isfinite(ranges) & (ranges > 0)]
    if len(ranges) == 0:
        raise ValueError("the first scan holds no valid point")
    return float(np.percentile(ranges, EXTENT_PERCENTILE)), float(ranges.max())


def _set_unset(model: BaseModel, field: str, value: float, changed: dict[str, float], path: str):
    if field not in model.model_fields_set:
        setattr(model, field, float(value))
        changed[f"{path}.{field}"] = float(value)


def scale_config(cfg: RunConfig, first_scan: np.ndarray) -> dict[str, float]:
    """Fill the scale-dependent fields ``cfg`` leaves unset (in place); returns what was set."""
    extent, farthest = scan_extent_m(first_scan)
    voxel = extent / 30.0
    changed: dict[str, float] = {}
    kiss_data = cfg.odometry.kiss_icp.data
    _set_unset(
        kiss_data, "max_range", max(farthest, 2.0 * extent), changed, "odometry.kiss_icp.data"
    )
    submaps = cfg.submaps
    for field, value in (
        ("max_range_m", MAP_RANGE_FACTOR * extent),
        ("loop_max_range_m", extent),
        ("max_distance_m", extent),
        ("localise_scan_spacing_m", extent / 10.0),
        ("map_voxel_m", voxel / 3.0),
        ("loop_voxel_m", voxel / 2.0),
        ("normal_radius_m", 1.5 * voxel),
    ):
        _set_unset(submaps, field, value, changed, "submaps")
    _set_unset(cfg.mapping, "voxel_size_m", voxel, changed, "mapping")
    _set_unset(cfg.loop_closure, "min_travel_m", 3.0 * extent, changed, "loop_closure")
    lidar = cfg.loop_closure.lidar
    for field, value in (
        ("proximity_radius_m", 0.7 * extent),
        ("icp_max_correspondence_m", 1.5 * voxel),
        ("density_map_resolution_m", voxel / 2.0),
        ("overlap_voxel_m", voxel),
        ("inlier_distance_m", voxel / 2.0),
    ):
        _set_unset(lidar, field, value, changed, "loop_closure.lidar")
    gravity = cfg.pose_graph.gravity
    for field, value in (
        ("voxel_m", voxel / 4.0),
        ("normal_radius_m", voxel),
        ("min_range_m", extent / 15.0),
        ("max_range_m", 5.0 * extent / 3.0),
    ):
        _set_unset(gravity, field, value, changed, "pose_graph.gravity")
    logger.info(
        "LiDAR scale from the first scan: extent %.1f m (p%.0f), farthest %.1f m; set %s",
        extent,
        EXTENT_PERCENTILE,
        farthest,
        ", ".join(f"{k}={v:.3g}" for k, v in changed.items()),
    )
    return changed
