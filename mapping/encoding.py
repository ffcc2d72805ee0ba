"""Encoding points with normals onto the world voxel grid (DESIGN 5.2).

Every point belongs to its 8 nearest voxels (the voxels whose ``2V`` cube around the centre
contains it). For voxel ``g`` the encoder sees ``r = (p - c_g) / V`` in ``[-1, 1]^3`` and the unit
normal; the voxel latent is the mean of the per-point latents, its weight the number of points,
and its Jacobian the mean of the exact per-point ``dF/dr``.

The Jacobian is computed by forward-mode differentiation written out for the two layer types of the
vector-neuron encoder (:class:`VNLinear`, :class:`VNLeakyReLU`), carrying the value and its three
tangents ``d/dr_j`` together in a channel-last layout ``(..., 3, C)`` so that every layer is one
matrix product. :func:`point_latents_reference` computes the same with ``torch.func`` and is used
by the tests to check the fast path.
"""

from __future__ import annotations

import torch
from torch import nn

from mapping import networks
from mapping.networks import PointEncoder, PriorModel, VNLeakyReLU, VNLinear
from mapping.voxel_block import VoxelBlock, pack_keys, unpack_keys

ENCODE_CHUNK = 2048
CORNER_OFFSETS = torch.tensor(
    [[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=torch.int64
)


def _vn_linear(weight: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Channel-last VNLinear: ``(..., 3, I) -> (..., 3, O)``."""
    return x @ weight.T


def _vn_leaky_relu(
    layer: VNLeakyReLU, x: torch.Tensor, dx: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Channel-last VN-LeakyReLU with optional forward-mode tangents ``dx (P, T, 3, C)``.

    With ``k = U x``, ``coef = <x, k> / (|k|^2 + eps)`` and ``a`` the slope, the module computes
    ``out = a x + (1 - a) relu`` where ``relu = x - coef k`` if ``<x, k> < 0`` else ``x``, i.e.
    ``out = x - beta k`` with ``beta = (1 - a) [<x, k> < 0] coef``. Its tangent is
    ``dx - gamma k - beta dk`` with ``gamma = (1 - a) [<x, k> < 0] d(coef)`` and
    ``d(coef) = <dx, k> + <x - 2 coef k, dk>`` over ``|k|^2 + eps``.
    """
    weight = layer.direction.weight
    k = _vn_linear(weight, x)
    dot = (x * k).sum(-2, keepdim=True)
    k_sq = (k * k).sum(-2, keepdim=True) + networks._EPS
    coef = dot / k_sq
    gate = (dot < 0).to(x.dtype) * (1.0 - layer.negative_slope)
    beta = gate * coef
    out = torch.addcmul(x, beta, k, value=-1.0)
    if dx is None:
        return out, None
    dk = _vn_linear(weight, dx)
    k1 = k.unsqueeze(1)
    y = torch.addcmul(x, coef, k, value=-2.0).unsqueeze(1)
    d_coef = ((dx * k1).sum(-2, keepdim=True) + (y * dk).sum(-2, keepdim=True)) / k_sq.unsqueeze(1)
    gamma = gate.unsqueeze(1) * d_coef
    d_out = torch.addcmul(dx, gamma, k1, value=-1.0)
    d_out.addcmul_(beta.unsqueeze(1), dk, value=-1.0)
    return out, d_out


def _run_branch(
    branch: nn.Sequential, x: torch.Tensor, dx: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor | None]:
    for layer in branch:
        if isinstance(layer, VNLinear):
            x = _vn_linear(layer.weight, x)
            dx = None if dx is None else _vn_linear(layer.weight, dx)
        elif isinstance(layer, VNLeakyReLU):
            x, dx = _vn_leaky_relu(layer, x, dx)
        else:
            raise TypeError(f"encoder layer {type(layer).__name__} has no fast path")
    return x, dx


def point_latents(
    encoder: PointEncoder, r: torch.Tensor, n: torch.Tensor, with_jacobian: bool
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Per-point latents in channel-last layout.

    Args:
        r: ``(P, 3)`` positions relative to the voxel centre (vu); n: ``(P, 3)`` unit normals.

    Returns:
        ``F (P, 3, C)`` with ``F[p, i, c]`` = component i of channel c, and, if asked,
        ``dF (P, 3, 3, C)`` with ``dF[p, j, i, c] = dF[p, i, c] / dr[p, j]``.
    """
    p = r.shape[0]
    eye = None
    if with_jacobian:
        eye = torch.eye(3, dtype=r.dtype, device=r.device).view(1, 3, 3, 1).expand(p, 3, 3, 1)
    if encoder.kind == "joint":
        x = torch.stack([r, n], dim=-1)
        dx = None if eye is None else torch.cat([eye, torch.zeros_like(eye)], dim=-1)
        return _run_branch(encoder.branch, x, dx)
    pos, d_pos = _run_branch(encoder.position, r.unsqueeze(-1), eye)
    nrm, _ = _run_branch(encoder.normal, n.unsqueeze(-1), None)
    out = torch.cat([pos, nrm], dim=-1)
    if d_pos is None:
        return out, None
    return out, torch.cat(
        [d_pos, torch.zeros(p, 3, 3, nrm.shape[-1], dtype=r.dtype, device=r.device)], -1
    )


def point_latents_reference(
    encoder: PointEncoder, r: torch.Tensor, n: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference via the module and ``torch.func.jacfwd``: ``(P, C, 3)``, ``(P, C, 3, 3)``."""

    def single(ri: torch.Tensor, ni: torch.Tensor) -> torch.Tensor:
        return encoder(ri, ni)

    latents = encoder(r, n)
    jac = torch.func.vmap(torch.func.jacfwd(single, argnums=0))(r, n)
    return latents, jac


def point_voxel_pairs(
    points: torch.Tensor, voxel_size_m: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The 8 voxels of every point: keys ``(N, 8, 3)``, ``r = p/V - (g + 1/2)`` ``(N, 8, 3)``.

    ``points`` should be float64: the fractional part is taken before casting so that ``r`` keeps
    full float32 precision far from the origin.
    """
    u = points.to(torch.float64) / voxel_size_m - 0.5
    base = torch.floor(u)
    frac = u - base
    offsets = CORNER_OFFSETS.to(points.device)
    grid = base.to(torch.int64).unsqueeze(1) + offsets
    r = frac.unsqueeze(1) - offsets.to(torch.float64)
    return grid, r


def prune_sparse_points(
    points: torch.Tensor, voxel_size_m: float, min_points_per_voxel: int
) -> torch.Tensor:
    """Boolean mask of points whose own voxel ``floor(p / V)`` holds ``>= min_points_per_voxel``."""
    if min_points_per_voxel <= 1 or points.shape[0] == 0:
        return torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
    own = torch.floor(points.to(torch.float64) / voxel_size_m).to(torch.int64)
    _, inverse, counts = torch.unique(pack_keys(own), return_inverse=True, return_counts=True)
    return counts[inverse] >= min_points_per_voxel


@torch.no_grad()
def encode_points(
    model: PriorModel,
    points_W: torch.Tensor,
    normals_W: torch.Tensor,
    voxel_size_m: float,
    *,
    min_points_per_voxel: int = 1,
    with_jacobian: bool = True,
    chunk: int = ENCODE_CHUNK,
) -> VoxelBlock:
    """Encode world points with unit normals onto the world grid (keys sorted, unique).

    The per-point work runs in chunks of ``chunk`` point-voxel pairs and is mean-pooled with
    ``index_add_``; nothing scales with the scene bounds.
    """
    encoder = model.encoder
    dtype = next(model.parameters()).dtype
    device = next(model.parameters()).device
    channels = model.latent_channels
    points_W = points_W.to(device)
    normals_W = normals_W.to(device)
    keep = prune_sparse_points(points_W, voxel_size_m, min_points_per_voxel)
    points_W, normals_W = points_W[keep], normals_W[keep]
    if points_W.shape[0] == 0:
        return VoxelBlock.empty(channels, device)
    grid, r = point_voxel_pairs(points_W, voxel_size_m)
    keys, inverse = torch.unique(pack_keys(grid.reshape(-1, 3)), return_inverse=True)
    r = r.reshape(-1, 3).to(dtype)
    n = normals_W.to(dtype).repeat_interleave(8, dim=0)
    m = keys.shape[0]
    sums = torch.zeros(m, 3, channels, dtype=dtype, device=device)
    jac_sums = torch.zeros(m, 3, 3, channels, dtype=dtype, device=device) if with_jacobian else None
    for start in range(0, r.shape[0], chunk):
        sl = slice(start, start + chunk)
        idx = inverse[sl]
        f, df = point_latents(encoder, r[sl], n[sl], with_jacobian)
        sums.index_add_(0, idx, f)
        if jac_sums is not None and df is not None:
            jac_sums.index_add_(0, idx, df)
    counts = torch.bincount(inverse, minlength=m).to(dtype)
    latents = (sums / counts.view(m, 1, 1)).transpose(1, 2)
    if jac_sums is None:
        jacobians = torch.zeros(m, channels, 3, 3, dtype=dtype, device=device)
    else:
        # jac_sums[m, j, i, c] -> J[m, c, i, j]
        jacobians = (jac_sums / counts.view(m, 1, 1, 1)).permute(0, 3, 2, 1)
    return VoxelBlock(
        keys=unpack_keys(keys),
        latents=latents.to(torch.float32).contiguous(),
        weights=counts.to(torch.float32),
        jacobians=jacobians.to(torch.float32).contiguous(),
    )
