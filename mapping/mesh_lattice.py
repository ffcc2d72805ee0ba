"""The meshing lattice: the nodes a voxel contributes to, and the coarse-to-fine decode.

A voxel's SDF reaches the lattice nodes strictly inside its ``2V`` cube (:func:`lattice_offsets`).
With more than two subdivisions, a chunk is first decoded on the coarse lattice of two; only the
fine nodes of the coarse cells that may hold surface (:func:`needed_fine_nodes`) are decoded
exactly, the others are interpolated from the coarse nodes (:func:`upsample`).
"""

from __future__ import annotations

import torch

NEAR_SURFACE_VU = 0.25  # coarse nodes closer than this to the surface mark their cells active


def lattice_offsets(subdivisions: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nodes strictly inside a voxel's ``2V`` cube.

    Returns ``(first, q, tent)``: ``first`` is the node index of the first node relative to
    ``g * s`` along each axis (int), ``q (Q, 3)`` the node offsets from the voxel centre in voxel
    units and ``tent (Q,)`` their trilinear weights; node ``j`` of voxel ``g`` is
    ``g * s + first + idx_j``.
    """
    s = subdivisions
    first = -(s // 2) + (0 if s % 2 else 1)  # smallest m - g s with |m - (g + 1/2) s| < s
    count = 2 * s - 1 if s % 2 == 0 else 2 * s
    axis = (torch.arange(count, dtype=torch.float64) + first - 0.5 * s) / s
    qa = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    idx = torch.arange(count)
    ia = torch.stack(torch.meshgrid(idx, idx, idx, indexing="ij"), dim=-1).reshape(-1, 3)
    tent = (1.0 - qa.abs()).prod(-1)
    return torch.tensor(first) + ia, qa.to(torch.float32), tent.to(torch.float32)


def normalise(
    num: torch.Tensor, den: torch.Tensor, sig: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Node values from the accumulated blend: ``(num / den, sig / den, den > 0)``."""
    valid = den > 0
    safe = torch.where(valid, den, torch.ones_like(den))
    return num / safe, sig / safe, valid


def needed_fine_nodes(
    c_sdf: torch.Tensor, c_valid: torch.Tensor, factor: int, n_fine: int
) -> torch.Tensor:
    """Fine nodes of the coarse cells that may hold surface (bool, ``(B, n, n, n)``).

    A coarse cell (half a voxel) is active when its observed corners change sign or one of them
    is closer than a quarter voxel to the surface. The coarse arrays carry one halo node on each
    side, so a chunk also knows the activity of its neighbours' cells along its faces and both
    chunks sharing a face agree on which face nodes are decoded exactly.
    """
    corners = [
        (
            slice(None),
            slice(i, i + c_sdf.shape[1] - 1),
            slice(j, j + c_sdf.shape[2] - 1),
            slice(k, k + c_sdf.shape[3] - 1),
        )
        for i in (0, 1)
        for j in (0, 1)
        for k in (0, 1)
    ]
    pos = torch.zeros_like(c_valid[corners[0]])
    neg = torch.zeros_like(pos)
    near = torch.zeros_like(pos)
    for idx in corners:
        v, ok = c_sdf[idx], c_valid[idx]
        pos |= ok & (v > 0)
        neg |= ok & (v < 0)
        near |= ok & (v.abs() < NEAR_SURFACE_VU)
    active = ((pos & neg) | near).to(torch.float32)  # (B, m, m, m) cells incl. the halo cells
    for dim in (1, 2, 3):
        active = active.repeat_interleave(factor, dim=dim)
    nodes = torch.nn.functional.max_pool3d(active.unsqueeze(1), 2, stride=1, padding=1)[:, 0]
    inner = slice(factor, factor + n_fine)
    return nodes[:, inner, inner, inner] > 0


def upsample(
    sdf: torch.Tensor, sigma: torch.Tensor, valid: torch.Tensor, n_fine: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Trilinear interpolation of coarse node arrays onto the fine nodes (corners aligned)."""

    def up(t: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.interpolate(
            t.unsqueeze(1), size=(n_fine,) * 3, mode="trilinear", align_corners=True
        )[:, 0]

    ok = up(valid.to(sdf.dtype)) > 1.0 - 1e-4
    fill_sdf = torch.where(valid, sdf, torch.zeros_like(sdf))
    fill_sigma = torch.where(valid, sigma, torch.zeros_like(sigma))
    return up(fill_sdf), up(fill_sigma), ok
