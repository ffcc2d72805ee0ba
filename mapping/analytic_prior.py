"""A hand-set (untrained) prior whose SDF is the local tangent plane: for tests and fallbacks.

With the default architecture, the encoder is set to copy its inputs (every VN-LeakyReLU gets the
identity as direction map, so ``<x, k> = |x|^2 >= 0`` and it passes ``x`` through): channel 0 of a
voxel latent is the mean point offset ``r_bar`` and channel 1 the mean normal ``n_bar``. The
decoder is set to output ``sdf(q) = n_bar . (q - r_bar)`` (through the invariants ``F q`` and the
Gram entry ``F_0 . F_1``; the softplus units run far in their linear regime) and a constant sigma.

So a planar surface is reproduced exactly, and since the latent is linear in the point positions
its Jacobian is exact and the first-order transform of a plane is exact as well. It is exactly
equivariant/invariant like any weights, which makes it a deterministic, meaningful stand-in for
the trained prior in tests (meshing, transform sign conventions) and when no weights are shipped.
"""

from __future__ import annotations

import torch

from mapping.networks import ModelConfig, PriorModel

_OFFSET = 6.0  # keeps every softplus(beta=10) unit in its linear regime for |sdf| < 5 vu
_SDF_RANGE_VU = 16.0
_SIGMA_LOGIT = -2.0  # sigma = 0.01 + softplus(-2) = 0.137 vu everywhere


@torch.no_grad()
def planar_prior() -> PriorModel:
    """The tangent-plane prior described in the module docstring (default architecture)."""
    cfg = ModelConfig(encoder_kind="joint", sdf_range_vu=_SDF_RANGE_VU)
    model = PriorModel(cfg)
    for p in model.parameters():
        p.zero_()
    branch = model.encoder.branch
    branch[0].weight[0, 0] = 1.0  # r
    branch[0].weight[1, 1] = 1.0  # n
    for idx in (1, 3):
        branch[idx].direction.weight.copy_(torch.eye(cfg.encoder_hidden))
    branch[2].weight.copy_(torch.eye(cfg.encoder_hidden))
    branch[4].weight[0, 0] = 1.0
    branch[4].weight[1, 1] = 1.0

    dec = model.decoder
    rows, cols = dec._rows.tolist(), dec._cols.tolist()
    g01 = next(i for i, (a, b) in enumerate(zip(rows, cols, strict=True)) if (a, b) == (0, 1))
    dec.gram_in.weight[0, g01] = -1.0  # - r_bar . n_bar
    dec.gram_in.bias[0] = _OFFSET
    dec.gram_in.bias[1] = _OFFSET
    dec.query_in.weight[0, 1] = 1.0  # + n_bar . q
    for layer in (dec.mlp[1], dec.mlp[3]):
        layer.weight[0, 0] = 1.0
        layer.weight[0, 1] = -1.0
        layer.bias[0] = _OFFSET
        layer.weight[1, 1] = 1.0
    last = dec.mlp[5]
    last.weight[0, 0] = 1.0 / _SDF_RANGE_VU
    last.weight[0, 1] = -1.0 / _SDF_RANGE_VU
    last.bias[1] = _SIGMA_LOGIT
    model.metadata = {"analytic": "planar"}
    return model
