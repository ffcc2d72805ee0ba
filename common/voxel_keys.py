"""Integer voxel coordinates packed into one int64 key: 21 bits per axis.

Coordinates ``g`` with ``|g| < KEY_LIMIT`` on every axis pack without collision; the numeric order
of keys is the lexicographic order of ``(x, y, z)``. Anything outside raises a ``ValueError``
naming the limit (a silently clipped key would merge far voxels into one): a caller that may see
far points legitimately must drop them itself before packing, and say so. Works on numpy arrays
and on torch tensors alike (same operators).
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)
KEY_MASK = (1 << KEY_BITS) - 1
KEY_LIMIT = KEY_OFFSET - 1
"""``|g|`` must stay below this on every axis (2**20 - 1 voxels)."""

Grid = TypeVar("Grid")  # np.ndarray or torch.Tensor of int64


def pack_keys(grid: Grid) -> Grid:
    """``(M, 3)`` int64 grid coordinates -> ``(M,)`` int64 keys (order = lexicographic order).

    Raises:
        ValueError: a coordinate has ``|g| >= KEY_LIMIT``.
    """
    # min/max rather than abs: abs() of the int64 that NaN and inf floor to stays negative
    if len(grid) and (int(grid.min()) <= -KEY_LIMIT or int(grid.max()) >= KEY_LIMIT):
        worst = max(-int(grid.min()), int(grid.max()))
        raise ValueError(
            f"voxel grid coordinate {worst} is beyond +-{KEY_LIMIT - 1} "
            f"({KEY_BITS}-bit voxel keys): the points span too many voxels; use a larger voxel "
            "size or drop the far points"
        )
    shifted = grid + KEY_OFFSET
    return (shifted[:, 0] << (2 * KEY_BITS)) | (shifted[:, 1] << KEY_BITS) | shifted[:, 2]


def unpack_keys(keys: Grid) -> Grid:
    """Inverse of :func:`pack_keys`: ``(M,)`` keys -> ``(M, 3)`` int64 grid coordinates."""
    columns = [keys >> (2 * KEY_BITS), (keys >> KEY_BITS) & KEY_MASK, keys & KEY_MASK]
    if isinstance(keys, np.ndarray):
        return np.stack(columns, axis=-1) - KEY_OFFSET
    import torch

    return torch.stack(columns, dim=-1) - KEY_OFFSET


def point_voxel_keys(points: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """One int64 key per ``(N, 3)`` point for the grid voxel containing it (see :func:`pack_keys`
    for the range; raises beyond it and for NaN or infinite coordinates)."""
    grid = np.floor(np.asarray(points) / voxel_size_m)
    if not np.isfinite(grid).all():
        raise ValueError("NaN or infinite point coordinates: drop them before voxelising")
    return pack_keys(grid.astype(np.int64))
