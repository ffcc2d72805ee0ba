"""SE(3) transform of a voxel block with first-order re-gridding: the paper's transform, corrected
(docs/design.md §3.5).

A block encoded on the world grid is moved by ``D`` (rotation ``R``, translation ``t``):

1. every source voxel centre moves, ``c' = D c``; its latent rotates, ``F' = F R^T``, and its mean
   Jacobian is conjugated, ``J' = R J R^T`` (per channel);
2. the moved centres are off the grid, so every world voxel ``t`` near them becomes a *target*.
   With ``v_i = (c_t - c'_i) / V`` (voxel units) the first-order hypothesis of source ``i`` for the
   target is ``h_i = F'_i - J'_i v_i`` (moving the reference centre by ``v`` shifts every relative
   point position by ``-v``);
3. ``F_t = sum_i s_i h_i`` and ``w_t = sum_i s_i w_i`` over the K nearest sources with normalised
   weights ``s``. Only when asked (``with_jacobians``) is the Jacobian of the target carried along
   by the same blend of the ``J'_i`` (zeroth order: second derivatives are not stored); a moved
   block goes into the global map, which keeps no Jacobians.

Weightings:

* ``gaussian`` (default): ``s = exp(-|v|^2 / 2 sigma^2) (1 - |v|^2)^2`` for ``|v| < 1`` vu, else 0.
  Compact support makes the transform *interpolating*: a source that lands exactly on a world
  centre (identity, integer-voxel translations, 90-degree rotations about lattice axes) is the only
  contributor there, so such motions reproduce re-encoding exactly. Measured on the two-path room
  benchmark (``benchmarks/bench_mapping.py``, trained prior) the mesh error falls slightly from
  ``sigma`` = 0.2 to 0.7 vu (0.207 -> 0.174 cm at 30 degrees) and is flat within 0.005 cm from
  0.5 on; the default is 0.5.
* ``uniform``: the paper's average over the K nearest sources (its ``exp(-d^2)`` with ``d`` in
  metres is practically uniform at V = 0.1 m), kept for comparison.

Targets: with ``cell`` (default for gaussian) a world voxel is a target iff its centre lies in the
moved cube (cell) of some source, i.e. the moved voxels are resampled on the world grid without
growing or shrinking the occupied volume; this is the nearest-source rule restricted to the source
lattice's Voronoi cells (the cubes themselves), so every target has a source within
``sqrt(3)/2`` vu. With ``radius`` (the paper's rule, default for uniform) a world voxel is a target
iff its nearest moved source is closer than one voxel; that adds a shell of extrapolated voxels
around the moved block (about 40 % more voxels on the room) and was worse in every run of the
two-path benchmark (e.g. 0.32 vs 0.20 cm path 1 -> path 2 at 3 degrees + 2.7 cm).

The blend is computed with sparse (target x source) matrices rather than by gathering each pair's
latent and Jacobian rows.
"""

from __future__ import annotations

import warnings
from typing import Literal

import numpy as np
import torch

from common.voxel_keys import pack_keys, unpack_keys
from mapping.voxel_block import VoxelBlock

_CELL_TOLERANCE = 1e-6
_DIST_LEVELS = 1 << 24  # distance quantisation of the single (target, distance) sort key


def _offsets(reach: int, device: torch.device) -> torch.Tensor:
    r = torch.arange(-reach, reach + 1, device=device)
    return torch.stack(torch.meshgrid(r, r, r, indexing="ij"), dim=-1).reshape(-1, 3)


def _csr(
    rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, n_rows: int, n_cols: int
) -> torch.Tensor:
    """A CSR matrix from entries whose ``rows`` are sorted (pairs are unique by construction)."""
    crow = torch.zeros(n_rows + 1, dtype=torch.int64, device=rows.device)
    crow[1:] = torch.cumsum(torch.bincount(rows, minlength=n_rows), 0)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(crow, cols, values, (n_rows, n_cols), check_invariants=False)


def check_rigid(T: np.ndarray, name: str = "T_delta") -> np.ndarray:
    """A 4x4 float64 rigid transform, or a one-line ``ValueError``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be a finite 4x4 rigid transform, got shape {T.shape}")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ValueError(f"{name} rotation is not orthonormal with det +1; re-orthonormalise it")
    return T


def transform_block(
    block: VoxelBlock,
    T_delta: np.ndarray,
    voxel_size_m: float,
    *,
    neighbors: int = 8,
    use_jacobian: bool = True,
    weighting: Literal["gaussian", "uniform"] = "gaussian",
    sigma_vu: float = 0.5,
    target_rule: Literal["cell", "radius"] | None = None,
    with_jacobians: bool = False,
) -> VoxelBlock:
    """Move a block by ``T_delta`` (world to world) and re-grid it onto the world voxel grid.

    Args:
        block: voxels encoded on the world grid.
        T_delta: 4x4 rigid transform applied to the block's content.
        voxel_size_m: the grid's voxel size V.
        neighbors: K, the number of nearest moved sources blended per target.
        use_jacobian: first-order hypotheses ``F' - J' v`` (else ``F'``).
        weighting: ``gaussian`` (compact, interpolating) or ``uniform`` (paper).
        sigma_vu: width of the gaussian weighting in voxel units.
        target_rule: ``cell`` or ``radius``; ``None`` picks ``cell`` for gaussian, ``radius`` for
            uniform (see the module docstring).
        with_jacobians: also return the blended, conjugated Jacobians of the targets.

    Returns:
        The re-gridded block (keys sorted and unique).
    """
    if block.jacobians is None and (use_jacobian or with_jacobians):
        raise ValueError("transform_block: the block has no Jacobians (needed by use_jacobian)")
    T = check_rigid(T_delta)
    if weighting not in ("gaussian", "uniform"):
        raise ValueError(f"unknown transform weighting '{weighting}' (gaussian or uniform)")
    rule = target_rule or ("cell" if weighting == "gaussian" else "radius")
    if rule not in ("cell", "radius"):
        raise ValueError(f"unknown target rule '{rule}' (cell or radius)")
    device = block.device
    if block.num_voxels == 0:
        return block if with_jacobians else block.without_jacobians()
    R64 = torch.as_tensor(T[:3, :3], device=device)
    t_vu = torch.as_tensor(T[:3, 3] / voxel_size_m, device=device)
    moved = (block.keys.to(torch.float64) + 0.5) @ R64.T + t_vu  # (M, 3) moved centres in vu

    # Candidate (source, target) pairs: world voxels around every moved centre. Offsets count
    # from the voxel holding the centre: small numbers that float32 holds to ~1e-7 vu, where the
    # centres themselves (keys up to 2^20) need float64.
    support_sq = 1.0 if weighting == "gaussian" else 3.0625  # (1.75 vu)^2 holds the 8 nearest
    reach = 1 if weighting == "gaussian" else 2
    nearest = torch.round(moved - 0.5).to(torch.int64)
    fraction = (moved - nearest).to(torch.float32)  # the centre within its voxel, [0, 1]
    offsets = _offsets(reach, device)
    v = (offsets.to(torch.float32) + 0.5) - fraction.unsqueeze(1)  # target minus moved source
    d_sq = (v * v).sum(-1)
    src, off = (d_sq < support_sq).nonzero(as_tuple=True)
    cand, d_sq = nearest[src] + offsets[off], d_sq[src, off]
    v_src = v[src, off] @ R64.to(torch.float32)  # offsets in the source frame, R^T v
    tgt_keys, tgt = torch.unique(pack_keys(cand), return_inverse=True)
    n_tgt = tgt_keys.shape[0]

    # Target selection.
    if rule == "cell":
        inside = v_src.abs().amax(-1) <= 0.5 + _CELL_TOLERANCE
    else:
        inside = d_sq < 1.0
    selected = torch.zeros(n_tgt, dtype=torch.bool, device=device)
    selected[tgt[inside]] = True

    # K nearest sources per target: one sort by (target, quantised distance), rank in each target.
    quantised = (d_sq * (_DIST_LEVELS / support_sq)).to(torch.int64).clamp_(0, _DIST_LEVELS - 1)
    order = torch.argsort(tgt * _DIST_LEVELS + quantised)
    tgt_sorted = tgt[order]
    counts = torch.bincount(tgt_sorted, minlength=n_tgt)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(order.shape[0], device=device) - starts[tgt_sorted]
    pair = order[(rank < neighbors) & selected[tgt_sorted]]

    new_index = torch.cumsum(selected.to(torch.int64), 0) - 1
    tgt_out = new_index[tgt[pair]]
    n_out = int(selected.sum())
    src_p = src[pair]
    if weighting == "gaussian":
        dp = d_sq[pair]
        s = torch.exp(-dp / (2.0 * sigma_vu**2)) * (1.0 - dp) ** 2
    else:
        s = torch.ones(pair.shape[0], dtype=torch.float32, device=device)
    den = torch.zeros(n_out, device=device).index_add_(0, tgt_out, s)
    s = s / den[tgt_out]

    # Blend with sparse (target x source) matrices instead of gathering every pair's rows:
    # F_t = S F - sum_d S_d J[..., d] with S_d = S * v_d, J_t = S J, w_t = S w.
    m = block.num_voxels
    channels = block.channels
    S = _csr(tgt_out, src_p, s, n_out, m)
    columns = [block.latents.reshape(m, -1), block.weights.view(m, 1)]
    if with_jacobians:
        columns.append(block.jacobians.reshape(m, -1))
    blended = S @ torch.cat(columns, dim=1)
    F = blended[:, : channels * 3]
    w = blended[:, channels * 3].contiguous()
    if use_jacobian:
        vp = v_src[pair]
        Sv = _csr(
            tgt_out.repeat_interleave(3),
            (src_p.unsqueeze(1) + torch.arange(3, device=device) * m).reshape(-1),
            (s.unsqueeze(1) * vp).reshape(-1),
            n_out,
            3 * m,
        )
        J_by_axis = block.jacobians.permute(3, 0, 1, 2).reshape(3 * m, channels * 3)
        F = F - Sv @ J_by_axis
    R32 = R64.to(torch.float32)
    jacobians = None
    if with_jacobians:
        # vec(R J R^T) = (R kron R) vec(J) for row-major 3x3 blocks
        J = blended[:, channels * 3 + 1 :]
        jacobians = (J.reshape(-1, 9) @ torch.kron(R32, R32).T).view(n_out, channels, 3, 3)
    return VoxelBlock(
        keys=unpack_keys(tgt_keys[selected]),
        latents=(F.reshape(-1, 3) @ R32.T).view(n_out, channels, 3),
        weights=w,
        jacobians=jacobians,
    )
