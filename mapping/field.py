"""Decoding the map's SDF: fast decoder paths and the blending of neighbouring voxels.

A voxel's latent is valid in the ``2V`` cube around its centre (that is where its points were).
At a world point ``p`` the (up to) 8 voxels whose cube contains ``p`` are decoded at
``q = (p - c_g) / V`` and blended with weights ``tent(q) / sigma`` where
``tent(q) = prod_a (1 - |q_a|)`` are the trilinear weights (they sum to one over the 8 voxels and
vanish on each cube's boundary, so the field is continuous) and ``sigma`` the predicted standard
deviation (the paper's rule: uncertain voxels get less say). Voxels lighter than the decode
threshold are ignored; a point is valid when at least one voxel contributes.
"""

from __future__ import annotations

import torch

from common.voxel_keys import pack_keys
from mapping.encoding import point_voxel_pairs
from mapping.networks import Decoder
from mapping.voxel_store import VoxelStore

DECODE_ROWS = 8192
QUERY_POINTS = 4096


def _finish(decoder: Decoder, out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    mean = decoder.sdf_range_vu * torch.tanh(out[..., 0])
    sigma = decoder.sigma_min_vu + torch.nn.functional.softplus(out[..., 1])
    return mean, sigma


def voxel_query_terms(decoder: Decoder, F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-voxel parts of the decoder's first layer: ``code (M, H)`` and ``A = W_proj F (M, H, 3)``.

    The first layer at query ``q`` is then ``code + A q + w_sq |q|^2``.
    """
    weight = decoder.query_in.weight  # (H, C + 1)
    return decoder.voxel_code(F), torch.einsum("hc,mcd->mhd", weight[:, : F.shape[1]], F)


def _sq_term(decoder: Decoder, q: torch.Tensor) -> torch.Tensor:
    return (q * q).sum(-1).unsqueeze(-1) * decoder.query_in.weight[:, -1]


@torch.no_grad()
def decode_lattice(
    decoder: Decoder,
    F: torch.Tensor,
    q: torch.Tensor,
    terms: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Decode every voxel ``F (M, C, 3)`` at the same offsets ``q (Q, 3)``: mean, sigma ``(M, Q)``.

    Equal to ``decoder(F, q)`` but the per-query first layer is ``code + A q + w |q|^2`` with the
    per-voxel ``A = W_proj F`` (``H x 3``), and the MLP runs on cache-sized row blocks. ``terms``:
    ``(code, A)`` of :func:`voxel_query_terms` where the caller has them already.
    """
    m = F.shape[0]
    n_q = q.shape[0]
    if m == 0:
        empty = torch.zeros(0, n_q, dtype=F.dtype, device=F.device)
        return empty, empty.clone()
    code, A = terms if terms is not None else voxel_query_terms(decoder, F)
    sq_term = _sq_term(decoder, q)  # (Q, H)
    mean = torch.empty(m, n_q, dtype=F.dtype, device=F.device)
    sigma = torch.empty_like(mean)
    step = max(1, DECODE_ROWS // n_q)
    for start in range(0, m, step):
        sl = slice(start, start + step)
        x = torch.matmul(q, A[sl].transpose(1, 2))  # (m, Q, H), laid out as the MLP reads it
        x += sq_term
        x += code[sl].unsqueeze(1)
        mean[sl], sigma[sl] = _finish(decoder, decoder.mlp(x))
    return mean, sigma


@torch.no_grad()
def decode_indexed(
    decoder: Decoder,
    code: torch.Tensor,
    A: torch.Tensor,
    q: torch.Tensor,
    voxel: torch.Tensor,
    offset: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Decode voxel ``voxel[i]`` at offset ``q[offset[i]]`` for every ``i`` (terms of
    :func:`voxel_query_terms`); returns mean and sigma ``(P,)``."""
    n = voxel.shape[0]
    mean = torch.empty(n, dtype=code.dtype, device=code.device)
    sigma = torch.empty_like(mean)
    w_sq = decoder.query_in.weight[:, -1]
    q_ext = torch.cat([q, (q * q).sum(-1, keepdim=True)], dim=1)  # (Q, 4): q and |q|^2
    axes = [A[..., d].contiguous() for d in range(3)]  # (M, H) each
    for start in range(0, n, DECODE_ROWS):
        sl = slice(start, start + DECODE_ROWS)
        v, k = voxel[sl], offset[sl]
        qk = q_ext.index_select(0, k)
        x = code.index_select(0, v)
        x.addcmul_(qk[:, 3:4], w_sq)
        for d in range(3):
            x.addcmul_(axes[d].index_select(0, v), qk[:, d : d + 1])
        mean[sl], sigma[sl] = _finish(decoder, decoder.mlp(x))
    return mean, sigma


@torch.no_grad()
def decode_pairs(
    decoder: Decoder, code: torch.Tensor, F: torch.Tensor, q: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Decode one query per row: ``code (P, H)``, ``F (P, C, 3)``, ``q (P, 3)`` -> ``(P,)`` each."""
    proj = (F * q.unsqueeze(1)).sum(-1)
    x = code + decoder.query_in(torch.cat([proj, (q * q).sum(-1, keepdim=True)], dim=-1))
    return _finish(decoder, decoder.mlp(x))


@torch.no_grad()
def query_field(
    store: VoxelStore,
    decoder: Decoder,
    points_W: torch.Tensor,
    voxel_size_m: float,
    min_weight: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Blended SDF mean and sigma (voxel units) and validity at world points ``(N, 3)``."""
    n = points_W.shape[0]
    device = store.device
    sdf = torch.zeros(n, dtype=torch.float32, device=device)
    sig = torch.zeros(n, dtype=torch.float32, device=device)
    valid = torch.zeros(n, dtype=torch.bool, device=device)
    for start in range(0, n, QUERY_POINTS):
        pts = points_W[start : start + QUERY_POINTS].to(device, torch.float64)
        grid, r = point_voxel_pairs(pts, voxel_size_m)
        rows = store.lookup(pack_keys(grid.reshape(-1, 3))).view(-1, 8)
        tent = (1.0 - r.abs()).prod(-1).to(torch.float32)  # (n, 8)
        use = (rows >= 0) & (tent > 0)
        use[use.clone()] = store.weights_at(rows[use]) >= min_weight
        if not bool(use.any()):
            continue
        uniq, inv = torch.unique(rows[use], return_inverse=True)
        F_u = store.latents_at(uniq)
        code = decoder.voxel_code(F_u)
        mean, sigma = decode_pairs(decoder, code[inv], F_u[inv], r[use].to(torch.float32))
        b = torch.zeros_like(tent)
        b[use] = tent[use] / sigma
        m_all = torch.zeros_like(tent)
        s_all = torch.zeros_like(tent)
        m_all[use] = mean
        s_all[use] = sigma
        den = b.sum(-1)
        ok = den > 0
        safe = torch.where(ok, den, torch.ones_like(den))
        sl = slice(start, start + pts.shape[0])
        sdf[sl] = torch.where(ok, (b * m_all).sum(-1) / safe, torch.zeros_like(den))
        sig[sl] = torch.where(ok, (b * s_all).sum(-1) / safe, torch.zeros_like(den))
        valid[sl] = ok
    return sdf, sig, valid
