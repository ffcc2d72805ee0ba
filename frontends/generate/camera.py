"""A pinhole RGB-D camera with Kinect-like depth noise (Nguyen et al. 2012)."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from frontends.frame import Intrinsics
from frontends.generate.raycast import Raycaster, rotate
from frontends.generate.scene import Scene
from frontends.generate.texture import surface_colour

# ICL-NUIM-like intrinsics at 640 x 480 (fy sign normalised); scaled for other image sizes.
BASE_WIDTH, BASE_HEIGHT = 640, 480
BASE_FX, BASE_FY = 481.2, 480.0


class RgbdCameraConfig(BaseModel):
    """Image size, depth range and noise of the simulated RGB-D camera."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    width: int = Field(640, ge=8, description="Image width in pixels.")
    height: int = Field(480, ge=8, description="Image height in pixels.")
    depth_scale: float = Field(5000.0, gt=0, description="PNG depth units per metre (TUM: 5000).")
    depth_min_m: float = Field(0.3, ge=0, description="Depth below this is invalid (0).")
    depth_max_m: float = Field(4.5, gt=0, description="Depth beyond this is invalid (0).")
    max_incidence_deg: float = Field(
        78.0,
        gt=0,
        le=90,
        description="Rays hitting a surface more obliquely than this are invalid.",
    )
    depth_noise: bool = Field(True, description="Add axial noise 0.0012 + 0.0019 (z - 0.4)^2 m.")
    dropout: float = Field(0.01, ge=0, lt=1, description="Probability a valid depth pixel is lost.")
    rgb_noise: float = Field(2.0, ge=0, description="Std-dev of colour noise, 8-bit units.")

    @property
    def intrinsics(self) -> Intrinsics:
        """ICL-like pinhole intrinsics scaled to this image size (principal point at the centre)."""
        return Intrinsics(
            fx=BASE_FX * self.width / BASE_WIDTH,
            fy=BASE_FY * self.height / BASE_HEIGHT,
            cx=(self.width - 1) / 2,
            cy=(self.height - 1) / 2,
            width=self.width,
            height=self.height,
        )


def kinect_depth_sigma(z_m: np.ndarray) -> np.ndarray:
    """Axial depth noise std-dev of a Kinect at depth ``z_m`` (Nguyen, Izadi, Lovell 2012)."""
    return 0.0012 + 0.0019 * (z_m - 0.4) ** 2


def unit_pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    """(H*W, 3) unit rays through the pixel centres, camera frame, row-major pixel order."""
    u, v = np.meshgrid(np.arange(intrinsics.width), np.arange(intrinsics.height))
    x = (u.ravel() - intrinsics.cx) / intrinsics.fx
    y = (v.ravel() - intrinsics.cy) / intrinsics.fy
    rays = np.stack([x, y, np.ones_like(x)], axis=1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def render_rgbd(
    raycaster: Raycaster,
    scene: Scene,
    T_W_C: np.ndarray,
    config: RgbdCameraConfig,
    rng: np.random.Generator,
    *,
    seed: int,
    unit_rays_C: np.ndarray | None = None,
    table: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Render at pose ``T_W_C`` -> (depth, rgb).

    ``depth`` is (H, W) uint16, metres * depth_scale, 0 = invalid; ``rgb`` is (H, W, 3) uint8.

    ``unit_rays_C`` (:func:`unit_pixel_rays`) and ``table`` (:func:`texture.face_table`) can be
    passed to reuse them across frames.
    """
    import cv2

    intr = config.intrinsics
    if unit_rays_C is None:
        unit_rays_C = unit_pixel_rays(intr)
    dirs_W = rotate(T_W_C[:3, :3], unit_rays_C)
    distance, face = raycaster.first_hit(T_W_C[:3, 3], dirs_W)
    hit = face >= 0
    z = np.where(hit, distance * unit_rays_C[:, 2], 0.0)

    normals = raycaster.face_normals[np.where(hit, face, 0)]
    cos_inc = np.abs(np.einsum("ij,ij->i", normals, dirs_W))
    if config.depth_noise:
        z = z + rng.standard_normal(len(z), dtype=np.float32) * kinect_depth_sigma(z)
    valid = hit & (cos_inc >= np.cos(np.deg2rad(config.max_incidence_deg)))
    valid &= (z >= config.depth_min_m) & (z <= config.depth_max_m)
    valid &= rng.random(len(z), dtype=np.float32) >= config.dropout
    depth = np.where(valid, np.round(z * config.depth_scale), 0.0)
    depth = np.clip(depth, 0, np.iinfo(np.uint16).max).astype(np.uint16)

    rgb = np.zeros((len(z), 3), np.float32)
    points_W = T_W_C[:3, 3] + dirs_W[hit] * distance[hit, None]
    rgb[hit] = surface_colour(scene, points_W, face[hit], seed=seed, table=table) * 255.0
    rgb = cv2.GaussianBlur(rgb.reshape(intr.height, intr.width, 3), (3, 3), 0.6)
    if config.rgb_noise > 0:
        rgb += rng.standard_normal(rgb.shape, dtype=np.float32) * np.float32(config.rgb_noise)
    rgb = np.clip(np.round(rgb), 0, 255).astype(np.uint8)
    return depth.reshape(intr.height, intr.width), rgb
