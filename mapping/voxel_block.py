"""A set of world-grid voxels with their latents.

Voxel ``g`` (integer grid coordinates) has centre ``(g + 1/2) V``. Sparse storage never allocates
anything over the scene bounds: voxels are identified by a packed int64 key
(:mod:`common.voxel_keys`, 21 bits per axis), whose numeric order is the lexicographic order of
``(x, y, z)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from common.voxel_keys import pack_keys


def _as_tensor(x: np.ndarray | torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(dtype)
    return torch.as_tensor(np.ascontiguousarray(x), dtype=dtype)


@dataclass
class VoxelBlock:
    """A set of world-grid voxels, rows sorted by packed key and unique.

    Attributes:
        keys: ``(M, 3)`` int64 grid coordinates.
        latents: ``(M, C, 3)`` float32 mean point latent per voxel.
        weights: ``(M,)`` float32 number of point-voxel associations (possibly interpolated);
            finite and positive.
        jacobians: ``(M, C, 3, 3)`` float32 mean ``dF/dr``: ``J[m, c, i, j] = dF[c, i] / dr[j]``
            with ``r`` the point position relative to the voxel centre in voxel units; ``None``
            where nothing will transform the block (the global map keeps none).

    A block is a transient working copy: what is kept for long is a
    :class:`~mapping.compact_block.CompactBlock` (packed keys, half-precision coefficients).
    """

    keys: torch.Tensor
    latents: torch.Tensor
    weights: torch.Tensor
    jacobians: torch.Tensor | None = None

    def __post_init__(self) -> None:
        self.keys = _as_tensor(self.keys, torch.int64)
        device = self.keys.device
        self.latents = _as_tensor(self.latents, torch.float32).to(device)
        self.weights = _as_tensor(self.weights, torch.float32).to(device)
        m = self.keys.shape[0]
        if self.keys.shape != (m, 3) or self.weights.shape != (m,):
            raise ValueError(f"VoxelBlock: keys {tuple(self.keys.shape)} / weights mismatch")
        if self.latents.ndim != 3 or self.latents.shape[0] != m or self.latents.shape[2] != 3:
            raise ValueError(
                f"VoxelBlock: latents must be (M, C, 3), got {tuple(self.latents.shape)}"
            )
        if m and not bool((self.weights > 0).all() and torch.isfinite(self.weights).all()):
            raise ValueError("VoxelBlock: weights must be finite and positive")
        if self.jacobians is not None:
            self.jacobians = _as_tensor(self.jacobians, torch.float32).to(device)
            c = self.latents.shape[1]
            if self.jacobians.shape != (m, c, 3, 3):
                raise ValueError(
                    f"VoxelBlock: jacobians must be (M, C, 3, 3), got {tuple(self.jacobians.shape)}"
                )

    @classmethod
    def empty(cls, channels: int, device: torch.device | str = "cpu") -> VoxelBlock:
        return cls(
            keys=torch.zeros(0, 3, dtype=torch.int64, device=device),
            latents=torch.zeros(0, channels, 3, device=device),
            weights=torch.zeros(0, device=device),
            jacobians=torch.zeros(0, channels, 3, 3, device=device),
        )

    def without_jacobians(self) -> VoxelBlock:
        return VoxelBlock(self.keys, self.latents, self.weights, None)

    @property
    def num_voxels(self) -> int:
        return int(self.keys.shape[0])

    @property
    def channels(self) -> int:
        return int(self.latents.shape[1])

    @property
    def device(self) -> torch.device:
        return self.keys.device

    def packed_keys(self) -> torch.Tensor:
        return pack_keys(self.keys)

    def to(self, device: torch.device | str) -> VoxelBlock:
        return VoxelBlock(
            self.keys.to(device),
            self.latents.to(device),
            self.weights.to(device),
            None if self.jacobians is None else self.jacobians.to(device),
        )

    def nbytes(self) -> int:
        """Bytes held by the arrays."""
        arrays = (self.keys, self.latents, self.weights, self.jacobians)
        return sum(t.element_size() * t.numel() for t in arrays if t is not None)

    def centers(self, voxel_size_m: float) -> np.ndarray:
        """``(M, 3)`` float64 world coordinates of the voxel centres."""
        return (self.keys.cpu().numpy().astype(np.float64) + 0.5) * voxel_size_m

    def select(self, index: torch.Tensor) -> VoxelBlock:
        """Rows ``index`` (a bool mask or sorted indices keep the key order)."""
        return VoxelBlock(
            self.keys[index],
            self.latents[index],
            self.weights[index],
            None if self.jacobians is None else self.jacobians[index],
        )
