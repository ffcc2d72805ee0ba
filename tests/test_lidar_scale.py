"""configs/lidar.yaml's scale-dependent fields come from the first scan unless set explicitly."""

from __future__ import annotations

import numpy as np
import pytest

from slam.app.config import default_config_path, load_run_config
from slam.app.lidar_scale import scale_config, scan_extent_m


def _ring_scan(radius_m: float, n: int = 5000) -> np.ndarray:
    rng = np.random.default_rng(0)
    r = rng.uniform(0.2 * radius_m, radius_m, n)
    angle = rng.uniform(0.0, 2 * np.pi, n)
    return np.stack([r * np.cos(angle), r * np.sin(angle), rng.normal(0.0, 0.5, n)], axis=1)


@pytest.mark.parametrize("radius_m", [10.0, 60.0])
def test_sizes_follow_the_scan_extent(radius_m: float) -> None:
    cfg = load_run_config(default_config_path("lidar"))
    scan = _ring_scan(radius_m)
    extent, farthest = scan_extent_m(scan)
    assert 0.8 * radius_m < extent < radius_m <= farthest + 1.0
    changed = scale_config(cfg, scan)
    assert cfg.mapping.voxel_size_m == pytest.approx(extent / 30.0)
    assert cfg.submaps.max_range_m == pytest.approx(extent)
    assert cfg.odometry.kiss_icp.data.max_range >= farthest
    assert cfg.loop_closure.min_travel_m == pytest.approx(3 * extent)
    assert "mapping.voxel_size_m" in changed


def test_explicit_values_win() -> None:
    cfg = load_run_config(
        default_config_path("lidar"),
        {"mapping": {"voxel_size_m": 0.25}, "submaps": {"max_range_m": 12.0}},
    )
    changed = scale_config(cfg, _ring_scan(60.0))
    assert cfg.mapping.voxel_size_m == 0.25 and cfg.submaps.max_range_m == 12.0
    assert "mapping.voxel_size_m" not in changed and "submaps.map_voxel_m" in changed
