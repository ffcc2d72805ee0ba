"""The point encoder evaluated exactly in the span of its input vectors (docs/design.md §3.2).

A vector-neuron layer only mixes channels (VNLinear) or subtracts from a channel a multiple of a
channel mix (VN-LeakyReLU), so every hidden channel is a combination of the input vectors (``r``
and ``n`` for the joint encoder). The layers run on the coefficients of that combination over the
orthogonal basis ``(n_hat, r_perp)``, ``r_perp = r - (r . n_hat) n_hat`` (two per channel instead
of three components; an orthogonal basis keeps the inner products as accurate as on 3-vectors),
the first activation takes ``k = U W x0`` straight from the input coefficients, and the 3-vectors
are formed once, after the last layer. The result is the module's (to float rounding), not an
approximation. The Jacobian is forward-mode differentiation along the invariants that depend on
``r`` (``r . n_hat`` and ``|r_perp|^2``), two scalar tangents instead of three vector ones, with
``dF/dr_j`` assembled from them at the end. tests/test_networks.py checks both against the
module and ``torch.func.jacfwd``.

:mod:`mapping.latent_table` tabulates this function once per prior; encoding looks it up.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from mapping import networks
from mapping.networks import PointEncoder, VNLeakyReLU, VNLinear


@dataclass
class _Span:
    """A branch's input channels written on an orthogonal basis of their span, per point.

    Attributes:
        basis: ``(P, 3)`` orthogonal basis vectors ``b_m``.
        gram: ``(P, 1)`` squared lengths ``|b_m|^2`` (the Gram matrix is diagonal; None: 1).
        inputs: ``(P | 1, I)`` coefficients ``X0[m]``: input channel c is ``sum_m X0[m][c] b_m``.
        d_inputs: per tangent invariant, the derivative of each ``X0[m]`` (None: zero).
        d_gram: per tangent invariant, the derivative of each ``|b_m|^2`` (None: zero).
        grads: per tangent invariant, its gradient with respect to ``r`` ``(P, 3)``.
        projected_out: with tangents, the last basis vector holds ``r``: its derivative is
            ``d b_last / dr = I - b_0 projected_out^T`` (None: the identity).
    """

    basis: list[torch.Tensor]
    gram: list[torch.Tensor | None]
    inputs: list[torch.Tensor]
    d_inputs: list[list[torch.Tensor | None]] = field(default_factory=list)
    d_gram: list[list[float | None]] = field(default_factory=list)
    grads: list[torch.Tensor] = field(default_factory=list)
    projected_out: torch.Tensor | None = None


def _joint_span(r: torch.Tensor, n: torch.Tensor, with_jacobian: bool) -> _Span:
    """``[r, n]`` on the orthogonal basis ``(n_hat, r_perp)``: ``r = t n_hat + r_perp`` with
    ``t = r . n_hat``, and ``n = |n| n_hat``.

    An orthogonal basis keeps every inner product a sum of products of coefficients that are
    themselves accurate (on the basis ``(r, n)`` the quadratic forms cancel badly where r is
    nearly parallel to n). Tangents are taken along ``t`` (gradient ``n_hat``) and
    ``|r_perp|^2`` (gradient ``2 r_perp``).
    """
    length = n.norm(dim=1, keepdim=True)
    n_hat = n / length
    t = (r * n_hat).sum(1, keepdim=True)
    r_perp = torch.addcmul(r, t, n_hat, value=-1.0)
    q = (r_perp * r_perp).sum(1, keepdim=True)
    span = _Span(
        basis=[n_hat, r_perp],
        gram=[None, q],
        inputs=[torch.cat([t, length], 1), r.new_tensor([[1.0, 0.0]])],
    )
    if with_jacobian:
        span.d_inputs = [[r.new_tensor([[1.0, 0.0]]), None], [None, None]]
        span.d_gram = [[None, None], [None, 1.0]]
        span.grads = [n_hat, 2.0 * r_perp]
        span.projected_out = n_hat  # d r_perp / dr = I - n_hat n_hat^T
    return span


def _single_span(v: torch.Tensor, is_r: bool, with_jacobian: bool) -> _Span:
    """One input channel ``v``; for ``v = r`` the tangent is along ``|r|^2`` (gradient ``2 r``)."""
    span = _Span(basis=[v], gram=[(v * v).sum(1, keepdim=True)], inputs=[v.new_ones(1, 1)])
    if with_jacobian and is_r:
        span.d_inputs = [[None]]
        span.d_gram = [[1.0]]
        span.grads = [2.0 * v]
    return span


def _linear(X: list[torch.Tensor], weight: torch.Tensor) -> list[torch.Tensor]:
    """VNLinear on span coefficients: every coefficient row maps like a channel vector."""
    return [x @ weight.T for x in X]


def _linear_tangents(
    dX: list[list[torch.Tensor | None]], weight: torch.Tensor
) -> list[list[torch.Tensor | None]]:
    return [[None if d is None else d @ weight.T for d in row] for row in dX]


def _relu_span(
    layer: VNLeakyReLU,
    span: _Span,
    X: list[torch.Tensor],
    dX: list[list[torch.Tensor | None]],
    K: list[torch.Tensor] | None = None,
    dK: list[list[torch.Tensor | None]] | None = None,
) -> tuple[list[torch.Tensor], list[list[torch.Tensor | None]]]:
    """VN-LeakyReLU on span coefficients, with tangents (``dX``; empty: none wanted).

    With ``k = U x``, ``coef = <x, k> / (|k|^2 + eps)`` and slope ``a``, the layer is
    ``x - beta k`` with ``beta = (1 - a) min(coef, 0)`` (``coef < 0`` exactly where
    ``<x, k> < 0``). Tangent: ``d_out = dx - d_beta k - beta dk`` with
    ``d_beta = (1 - a) [coef < 0] (d<x, k> - coef d|k|^2) / (|k|^2 + eps)``, where the inner
    products ``sum_m |b_m|^2 x_m k_m`` also change with the basis lengths. ``K``/``dK`` may be
    given when the caller has them more cheaply (the first layer).
    """
    slope = 1.0 - layer.negative_slope
    U = layer.direction.weight
    K = _linear(X, U) if K is None else K
    GK = [k if g is None else g * k for g, k in zip(span.gram, K, strict=True)]
    k_sq = torch.addcmul(K[0].new_tensor(networks._EPS), K[0], GK[0])  # per point: (P, C)
    coef = X[0] * GK[0]
    for m in range(1, len(X)):
        k_sq.addcmul_(K[m], GK[m])
        coef.addcmul_(X[m], GK[m])
    coef.div_(k_sq)
    beta = coef.clamp(max=0.0)  # times slope, which the products below apply
    out = [torch.addcmul(x, beta, k, value=-slope) for x, k in zip(X, K, strict=True)]
    if not dX:
        return out, []
    gate = coef.neg().sign_().clamp_(min=0.0).mul_(slope)  # (1 - a) [coef < 0], no bool pass
    dK = _linear_tangents(dX, U) if dK is None else dK
    GX = [x if g is None else g * x for g, x in zip(span.gram, X, strict=True)]
    d_out = []
    for dx_row, dk_row, dg_row in zip(dX, dK, span.d_gram, strict=True):
        d_dot = torch.zeros_like(coef)
        d_ksq = torch.zeros_like(coef)
        terms = zip(X, K, GK, GX, dx_row, dk_row, dg_row, strict=True)
        for x, k, gk, gx, dx, dk, dg in terms:
            if dx is not None:
                d_dot.addcmul_(dx, gk)
            if dk is not None:
                d_dot.addcmul_(gx, dk)
                d_ksq.addcmul_(gk, dk, value=2.0)
            if dg is not None:
                d_dot.addcmul_(x, k, value=dg)
                d_ksq.addcmul_(k, k, value=dg)
        d_beta = d_dot.addcmul_(coef, d_ksq, value=-1.0).div_(k_sq).mul_(gate)
        row = []
        for k, dx, dk in zip(K, dx_row, dk_row, strict=True):
            d = torch.mul(d_beta, k).neg_()
            if dx is not None:
                d.add_(dx)
            if dk is not None:
                d.addcmul_(beta, dk, value=-slope)
            row.append(d)
        d_out.append(row)
    return out, d_out


def combine(vectors: list[torch.Tensor], coefficients: list[torch.Tensor]) -> torch.Tensor:
    """``out[p, i] = sum_m vectors[m][p, i] coefficients[m][p]``: ``(P, 3, D)`` from ``(P, 3)``
    vectors and ``(P, D)`` coefficients, one component at a time (a broadcast outer product over
    two dimensions is about 2.5x slower on CPU)."""
    out = coefficients[0].new_empty(coefficients[0].shape[0], 3, coefficients[0].shape[1])
    for i in range(3):
        component = out[:, i]
        torch.mul(coefficients[0], vectors[0][:, i : i + 1], out=component)
        for vector, coefficient in zip(vectors[1:], coefficients[1:], strict=True):
            component.addcmul_(vector[:, i : i + 1], coefficient)
    return out


def _branch_latents(
    branch: nn.Sequential, span: _Span, with_jacobian: bool
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """One vector-neuron branch on the span of its input channels.

    VNLinear mixes channels and VN-LeakyReLU subtracts a multiple of a channel mix, so every
    channel of every layer stays in the span of the input channels: the branch runs on the
    coefficients ``X[m]`` (``(P, C)``, or ``(1, C)`` while the same for every point) on the basis
    ``span.basis``, and the 3-vectors are formed once, at the end. The first activation takes
    ``k = U W x0`` straight from the few input coefficients.

    Returns ``F (P, 3, C)`` and, with ``with_jacobian``, ``dF (P, 3 i, 3 j, C) = dF_ic / dr_j``
    (zeros when the branch does not see r).
    """
    P = span.basis[0].shape[0]
    X, dX = span.inputs, span.d_inputs
    layers = list(branch)
    K = dK = None
    for index, layer in enumerate(layers):
        if isinstance(layer, VNLinear):
            nxt = layers[index + 1] if index + 1 < len(layers) else None
            if index == 0 and isinstance(nxt, VNLeakyReLU):
                UW = nxt.direction.weight @ layer.weight
                K, dK = _linear(X, UW), _linear_tangents(dX, UW)
            X, dX = _linear(X, layer.weight), _linear_tangents(dX, layer.weight)
        elif isinstance(layer, VNLeakyReLU):
            X, dX = _relu_span(layer, span, X, dX, K, dK)
            K = dK = None
        else:
            raise TypeError(f"encoder layer {type(layer).__name__} has no span form")
    X = [x.expand(P, -1) for x in X]
    channels = X[0].shape[1]
    F = combine(span.basis, X)
    if not with_jacobian:
        return F, None
    if not span.grads:
        return F, F.new_zeros(P, 3, 3, channels)
    # dF[i, j] = sum_m b_m[i] Z_m[j] + (d b_last[i] / d r_j) X[last], with
    # Z_m[j] = sum_tau d(tau)/dr_j dX[tau][m]; d b_last / dr = I - b_0 projected_out^T, whose
    # second part goes into Z_0
    Z = []
    for m in range(len(X)):
        grads, values = [], []
        for grad, row in zip(span.grads, dX, strict=True):
            if row[m] is not None:
                grads.append(grad)
                values.append(row[m].expand(P, -1))
        if m == 0 and span.projected_out is not None:
            grads.append(span.projected_out)
            values.append(-X[-1])
        if not grads:  # coefficient m does not depend on r (only in a branch without activations)
            grads, values = [span.grads[0]], [X[m].new_zeros(P, channels)]
        Z.append(combine(grads, values).view(P, 3 * channels))
    dF = combine(span.basis, Z).view(P, 3, 3, channels)
    torch.diagonal(dF, dim1=1, dim2=2).add_(X[-1].unsqueeze(-1))
    return F, dF


@torch.no_grad()
def point_latents(
    encoder: PointEncoder, r: torch.Tensor, n: torch.Tensor, with_jacobian: bool
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Per-point latents in channel-last layout, and their Jacobians if asked (no autograd:
    the Jacobians are computed explicitly).

    Args:
        r: ``(P, 3)`` positions relative to the voxel centre (vu); n: ``(P, 3)`` unit normals.

    Returns:
        ``F (P, 3, C)`` with ``F[p, i, c]`` = component i of channel c, and, if asked,
        ``dF (P, 3, 3, C)`` with ``dF[p, i, j, c] = dF[p, i, c] / dr[p, j]``.
    """
    if encoder.kind == "joint":
        return _branch_latents(encoder.branch, _joint_span(r, n, with_jacobian), with_jacobian)
    pos, d_pos = _branch_latents(
        encoder.position, _single_span(r, True, with_jacobian), with_jacobian
    )
    nrm, _ = _branch_latents(encoder.normal, _single_span(n, False, False), False)
    latents = torch.cat([pos, nrm], dim=-1)
    if d_pos is None:
        return latents, None
    return latents, torch.cat([d_pos, d_pos.new_zeros(*d_pos.shape[:-1], nrm.shape[-1])], dim=-1)
