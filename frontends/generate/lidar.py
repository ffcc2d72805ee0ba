"""A simulated 64-beam rotating LiDAR (HDL-64E-like) with range noise and dropouts."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from frontends.generate.raycast import Raycaster, rotate
from frontends.generate.scene import Scene


class LidarConfig(BaseModel):
    """Scanner geometry and noise. Defaults approximate a Velodyne HDL-64E as used in KITTI."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    beams: int = Field(64, ge=1, description="Number of laser beams (rows).")
    elevation_max_deg: float = Field(2.0, description="Elevation of the highest beam, degrees.")
    elevation_min_deg: float = Field(-24.8, description="Elevation of the lowest beam, degrees.")
    azimuth_steps: int = Field(
        2048, ge=8, description="Firings per revolution (columns); lower it for fast tests."
    )
    range_min_m: float = Field(0.5, gt=0, description="Returns closer than this are dropped.")
    range_max_m: float = Field(100.0, gt=0, description="Returns farther than this are dropped.")
    range_noise_m: float = Field(0.02, ge=0, description="Std-dev of gaussian range noise, m.")
    dropout: float = Field(0.02, ge=0, lt=1, description="Probability a valid return is lost.")


def beam_directions(config: LidarConfig) -> np.ndarray:
    """(azimuth_steps * beams, 3) unit ray directions in the sensor frame (x fwd, y left, z up).

    Ordered firing by firing: azimuth sweeps clockwise seen from above starting behind the
    sensor (like KISS-ICP's KITTI timestamp convention), all beams top to bottom per firing.
    """
    elevation = np.deg2rad(
        np.linspace(config.elevation_max_deg, config.elevation_min_deg, config.beams)
    )
    azimuth = np.pi - 2 * np.pi * (np.arange(config.azimuth_steps) + 0.5) / config.azimuth_steps
    az, el = np.meshgrid(azimuth, elevation, indexing="ij")
    return np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1
    ).reshape(-1, 3)


def simulate_scan(
    raycaster: Raycaster,
    scene: Scene,
    T_W_S: np.ndarray,
    config: LidarConfig,
    rng: np.random.Generator,
    directions_S: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One scan at pose ``T_W_S``: (N, 3) float64 points in the sensor frame and (N,) reflectance.

    Noise is added along each ray; ``rng`` drives noise, dropouts and reflectance jitter.
    """
    if directions_S is None:
        directions_S = beam_directions(config)
    directions_W = rotate(T_W_S[:3, :3], directions_S)
    distance, face = raycaster.first_hit(T_W_S[:3, 3], directions_W)
    noisy = distance + rng.normal(0.0, config.range_noise_m, len(distance))
    keep = (face >= 0) & (noisy >= config.range_min_m) & (noisy <= config.range_max_m)
    keep &= rng.random(len(distance)) >= config.dropout
    points = directions_S[keep] * noisy[keep, None]
    cos_incidence = np.abs(
        np.einsum("ij,ij->i", directions_W[keep], raycaster.face_normals[face[keep]])
    )
    reflectance = scene.face_reflectance[face[keep]] * (0.4 + 0.6 * cos_incidence)
    reflectance = reflectance + rng.normal(0.0, 0.02, len(reflectance))
    return points, np.clip(np.round(reflectance, 2), 0.0, 1.0)
