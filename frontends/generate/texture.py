"""Procedural surface colour: a deterministic function of world position, so views agree.

Each face has a base colour and a texture cell size. Surfaces are tiled in the plane of their
dominant normal axis with cells of random colour (a hash of the integer cell coordinates and the
seed) modulated by finer random-intensity cells; this gives corners everywhere for ORB features.
A fixed point light adds view-independent Lambertian shading.
"""

from __future__ import annotations

import numpy as np

from frontends.generate.scene import Scene

_MASK64 = (1 << 64) - 1


def _hash64(keys: list[np.ndarray], salt: int) -> np.ndarray:
    """Well-mixed uint64 hashes of integer keys (SplitMix-style mixing, wrapping arithmetic)."""
    h = np.full(keys[0].shape, (salt * 0x9E3779B97F4A7C15) & _MASK64, dtype=np.uint64)
    for key in keys:
        h ^= key.astype(np.int64).view(np.uint64)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(31)
        h *= np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(29)
    return h


def _bits01(h: np.ndarray, shift: int) -> np.ndarray:
    """Uniform [0, 1) float32 from 16 bits of ``h`` starting at bit ``shift``."""
    return ((h >> np.uint64(shift)) & np.uint64(0xFFFF)).astype(np.float32) / np.float32(65536.0)


def face_table(scene: Scene) -> np.ndarray:
    """(F, 8) float32 per-face record: normal (3), albedo (3), 1 / cell size (0 = plain), axis."""
    normals = np.asarray(scene.mesh.face_normals, np.float32)
    cell = scene.face_texture_m
    inv_cell = np.where(cell > 0, 1.0 / np.where(cell > 0, cell, 1.0), 0.0)
    axis = np.argmax(np.abs(normals), axis=1)
    return np.column_stack([normals, scene.face_albedo, inv_cell, axis]).astype(np.float32)


def surface_colour(
    scene: Scene,
    points_W: np.ndarray,
    face: np.ndarray,
    *,
    seed: int,
    light_W: tuple[float, float, float] = (0.0, 0.0, 2.8),
    table: np.ndarray | None = None,
) -> np.ndarray:
    """(N, 3) float32 RGB in [0, 1] of the surface points ``points_W`` on faces ``face``.

    ``table`` (from :func:`face_table`) can be passed to reuse it across frames.
    """
    rec = (face_table(scene) if table is None else table)[face]
    normals, albedo, inv_cell, axis = rec[:, 0:3], rec[:, 3:6], rec[:, 6], rec[:, 7]
    p = points_W.astype(np.float32)
    # Plane coordinates in the plane of the dominant normal axis: x->(y, z), y->(x, z), z->(x, y).
    u = np.where(axis == 0, p[:, 1], p[:, 0])
    v = np.where(axis == 2, p[:, 1], p[:, 2])
    axis_key = axis.astype(np.int64)
    cell_key = np.round(inv_cell * 16).astype(np.int64)
    h = _hash64(
        [
            np.floor(u * inv_cell).astype(np.int64),
            np.floor(v * inv_cell).astype(np.int64),
            axis_key,
            cell_key,
        ],
        2 * seed + 1,
    )
    h_fine = _hash64(
        [
            np.floor(2 * u * inv_cell).astype(np.int64),
            np.floor(2 * v * inv_cell).astype(np.int64),
            axis_key,
        ],
        2 * seed + 2,
    )
    cell_rgb = np.stack([_bits01(h, 0), _bits01(h, 16), _bits01(h, 32)], axis=1)
    fine_gain = np.float32(0.55) + np.float32(0.45) * _bits01(h_fine, 0)
    textured = (inv_cell > 0)[:, None]
    colour = np.where(textured, (0.45 * albedo + 0.55 * cell_rgb) * fine_gain[:, None], albedo)
    to_light = np.asarray(light_W, np.float32) - p
    dist2 = np.einsum("ij,ij->i", to_light, to_light)
    lambert = np.clip(np.einsum("ij,ij->i", normals, to_light) / np.sqrt(dist2), 0.0, 1.0)
    shade = np.float32(0.35) + np.float32(0.8) * lambert / (
        np.float32(1.0) + np.float32(0.04) * dist2
    )
    return np.clip(colour * shade[:, None], 0.0, 1.0)
