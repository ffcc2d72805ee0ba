"""The point encoder as a table over its two invariants (docs/design.md §3.2).

Every channel of the encoder stays in the span of ``r`` and ``n`` (:mod:`mapping.span_encoder`)
and the encoder is rotation equivariant, so for a unit normal ``n`` a point's latent is

    ``F(r, n) = A(t, s) n + B(t, s) r_hat``,  with ``t = r . n``, ``s = |r_perp|``,
    ``r_perp = r - t n``, ``r_hat = r_perp / s``:

two functions of two scalars per channel. ``r`` lies in ``[-1, 1]^3``, so ``(t, s)`` lies in
``[-sqrt 3, sqrt 3] x [0, sqrt 3]``. :class:`LatentTable` samples ``A``, ``B`` and their partial
derivatives on a ``nodes x nodes`` grid of that rectangle with the exact span encoder (at
``r = t e_z + s e_x``, ``n = e_z``), once per prior; a point's latent is then a bilinear
interpolation of four table rows instead of a pass through the network.

``B`` is the coefficient of the unit vector ``r_hat``, not of ``r_perp``: where a VN-LeakyReLU's
direction ``k`` nearly vanishes for ``r`` along ``n``, the coefficient of ``r_perp`` grows like
``1 / s``, and interpolating it failed there by up to 10x the latent.

The Jacobian is the exact one of this form,
``dF_i/dr_j = n_i dA/dr_j + r_hat_i dB/dr_j + (B / s) (delta_ij - n_i n_j - r_hat_i r_hat_j)``
with ``dA/dr = A_t n + A_s r_hat`` (likewise ``B``), from the interpolated partials.

Equivariance is untouched (the table holds invariants; the basis vectors rotate with the
scene). Interpolation error, shipped prior, 256 nodes, 30k-point depth frame: voxel latents
median 1.7e-5, largest 2.1e-4 relative; voxel Jacobians median 0.3 %, against 6 % between the
default 16-pair Jacobian sample and every pair (BENCHMARKS.md, LiDAR throughput,
micro-benchmarks). The unit normal matters: ``A`` and ``B`` are tabulated for ``|n| = 1``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from mapping.networks import PointEncoder
from mapping.span_encoder import combine, point_latents

_SQRT3 = math.sqrt(3.0)
_TINY = 1e-12  # s below this is r along n: r_hat is taken as 0 (B vanishes there)
UNIT_NORMAL_TOLERANCE = 1e-4


@dataclass(frozen=True)
class LatentTable:
    """``A``, ``B`` and their partials on a ``nodes x nodes`` grid of ``(t, s)``.

    Attributes:
        nodes: grid nodes per axis; node ``(i, j)`` is row ``i * nodes + j`` at
            ``t = -sqrt 3 + 2 sqrt 3 i / (nodes - 1)``, ``s = sqrt 3 j / (nodes - 1)``.
        values: ``(nodes^2, 2C)``: ``[A | B]``.
        partials: ``(nodes^2, 4C)``: ``[dA/dt | dA/ds | dB/dt | dB/ds]``.
    """

    nodes: int
    values: torch.Tensor
    partials: torch.Tensor

    @property
    def channels(self) -> int:
        return self.values.shape[1] // 2

    @staticmethod
    @torch.no_grad()
    def build(encoder: PointEncoder, nodes: int, chunk: int = 4096) -> LatentTable:
        """Sample the exact span encoder on the grid (in the encoder's dtype and device)."""
        if nodes < 2:
            raise ValueError(f"a latent table needs at least 2 nodes per axis, got {nodes}")
        param = next(encoder.parameters())
        like = {"dtype": param.dtype, "device": param.device}
        t, s = torch.meshgrid(
            torch.linspace(-_SQRT3, _SQRT3, nodes, **like),
            torch.linspace(0.0, _SQRT3, nodes, **like),
            indexing="ij",
        )
        r = torch.zeros(nodes * nodes, 3, **like)
        r[:, 2], r[:, 0] = t.reshape(-1), s.reshape(-1)
        n = torch.zeros_like(r)
        n[:, 2] = 1.0
        values, partials = [], []
        for start in range(0, r.shape[0], chunk):
            F, dF = point_latents(encoder, r[start : start + chunk], n[start : start + chunk], True)
            # here n = e_z and r_hat = e_x, and moving r along e_z (e_x) changes only t (s)
            values.append(torch.cat([F[:, 2], F[:, 0]], 1))
            partials.append(torch.cat([dF[:, 2, 2], dF[:, 2, 0], dF[:, 0, 2], dF[:, 0, 0]], 1))
        return LatentTable(nodes, torch.cat(values), torch.cat(partials))

    def _corners(self, t: torch.Tensor, s: torch.Tensor) -> tuple[list[torch.Tensor], list]:
        """Rows of the four grid nodes around each ``(t, s)`` and their bilinear weights."""
        last = self.nodes - 1
        u = (t + _SQRT3) * (last / (2.0 * _SQRT3))
        v = s * (last / _SQRT3)
        i = u.floor().clamp_(0, last - 1)
        j = v.floor().clamp_(0, last - 1)
        a = (u - i).clamp_(0.0, 1.0)
        b = (v - j).clamp_(0.0, 1.0)
        row = (i * self.nodes + j).squeeze(1).to(torch.int64)
        rows = [row, row + 1, row + self.nodes, row + self.nodes + 1]
        weights = [(1.0 - a) * (1.0 - b), (1.0 - a) * b, a * (1.0 - b), a * b]
        return rows, weights

    @staticmethod
    def _interpolate(table: torch.Tensor, rows: list, weights: list) -> torch.Tensor:
        out = table.index_select(0, rows[0]).mul_(weights[0])
        for row, weight in zip(rows[1:], weights[1:], strict=True):
            out.addcmul_(table.index_select(0, row), weight)
        return out

    def latents(
        self, r: torch.Tensor, n: torch.Tensor, with_jacobian: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:func:`mapping.span_encoder.point_latents` for unit normals, by table lookup:
        ``F (P, 3, C)`` and, if asked, ``dF (P, 3 i, 3 j, C) = dF_ic / dr_j``."""
        C = self.channels
        t = (r * n).sum(1, keepdim=True)
        r_perp = torch.addcmul(r, t, n, value=-1.0)
        s = r_perp.norm(dim=1, keepdim=True)
        s_safe = s.clamp(min=_TINY)
        basis = [n, r_perp / s_safe]
        rows, weights = self._corners(t, s)
        X = self._interpolate(self.values, rows, weights)
        F = combine(basis, [X[:, :C], X[:, C:]])
        if not with_jacobian:
            return F, None
        P = r.shape[0]
        D = self._interpolate(self.partials, rows, weights)
        b_over_s = X[:, C:] / s_safe
        z_n = combine(basis, [D[:, :C] - b_over_s, D[:, C : 2 * C]]).view(P, 3 * C)
        z_hat = combine(basis, [D[:, 2 * C : 3 * C], D[:, 3 * C :] - b_over_s]).view(P, 3 * C)
        dF = combine(basis, [z_n, z_hat]).view(P, 3, 3, C)
        torch.diagonal(dF, dim1=1, dim2=2).add_(b_over_s.unsqueeze(-1))
        return F, dF


def latent_table(encoder: PointEncoder, nodes: int) -> LatentTable:
    """The encoder's table, built on first use and kept on the encoder object until its weights,
    dtype or device change (parameter versions count in-place updates)."""
    param = next(encoder.parameters())
    key = (
        nodes,
        param.dtype,
        param.device,
        tuple(p._version for p in encoder.parameters()),
    )
    cached = encoder.__dict__.get("_latent_table")
    if cached is None or cached[0] != key:
        cached = (key, LatentTable.build(encoder, nodes))
        encoder.__dict__["_latent_table"] = cached
    return cached[1]
