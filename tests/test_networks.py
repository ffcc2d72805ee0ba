"""Exact SO(3) equivariance of the encoder, invariance of the decoder, and the fast paths."""

from __future__ import annotations

import pytest
import torch
from scipy.spatial.transform import Rotation

from mapping.field import decode_lattice, decode_pairs
from mapping.networks import ModelConfig, PriorModel
from mapping.span_encoder import point_latents


def _rotations(n: int, seed: int) -> torch.Tensor:
    return torch.tensor(Rotation.random(n, random_state=seed).as_matrix(), dtype=torch.float32)


def _inputs(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    r = torch.rand(n, 3, generator=g) * 2 - 1
    normal = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return r, normal


@pytest.mark.parametrize("kind", ["joint", "two_branch"])
def test_encoder_is_rotation_equivariant(kind: str) -> None:
    torch.manual_seed(1)
    model = PriorModel(ModelConfig(encoder_kind=kind)).eval()
    r, n = _inputs(256, 0)
    with torch.no_grad():
        base = model.encoder(r, n)
        for R in _rotations(5, 3):
            rotated = model.encoder(r @ R.T, n @ R.T)
            assert (rotated - base @ R.T).abs().max() < 1e-5


def test_decoder_is_rotation_invariant() -> None:
    torch.manual_seed(2)
    model = PriorModel().eval()
    g = torch.Generator().manual_seed(4)
    F = torch.randn(32, model.latent_channels, 3, generator=g)
    q = torch.rand(32, 20, 3, generator=g) * 2 - 1
    with torch.no_grad():
        mean, sigma = model.decoder(F, q)
        assert mean.abs().max() > 1e-3  # not a constant field
        for R in _rotations(5, 5):
            mean_r, sigma_r = model.decoder(F @ R.T, q @ R.T)
            assert (mean_r - mean).abs().max() < 1e-5
            assert (sigma_r - sigma).abs().max() < 1e-5
            assert (sigma > 0).all()


@pytest.mark.parametrize("kind", ["joint", "two_branch"])
def test_fast_encoder_matches_module_and_autodiff(kind: str) -> None:
    torch.manual_seed(3)
    model = PriorModel(ModelConfig(encoder_kind=kind)).double().eval()
    r, n = _inputs(300, 1)
    r, n = r.double(), n.double()
    fast, d_fast = point_latents(model.encoder, r, n, with_jacobian=True)
    ref = model.encoder(r, n)
    jac_ref = torch.func.vmap(torch.func.jacfwd(model.encoder, argnums=0))(r, n)
    assert torch.allclose(fast.transpose(1, 2), ref, atol=1e-12, rtol=0)
    # dF[p, i, j, c] -> J[p, c, i, j]
    assert torch.allclose(d_fast.permute(0, 3, 1, 2), jac_ref, atol=1e-10, rtol=0)
    assert jac_ref.abs().max() > 1e-3
    only, none = point_latents(model.encoder, r, n, with_jacobian=False)
    assert none is None and torch.equal(only, fast)


def test_fast_decoders_match_module() -> None:
    torch.manual_seed(4)
    model = PriorModel().eval()
    g = torch.Generator().manual_seed(6)
    F = torch.randn(50, model.latent_channels, 3, generator=g)
    q = torch.rand(27, 3, generator=g) * 2 - 1
    with torch.no_grad():
        mean_ref, sigma_ref = model.decoder(F, q.expand(50, 27, 3))
        mean, sigma = decode_lattice(model.decoder, F, q)
        assert torch.allclose(mean, mean_ref, atol=1e-5) and torch.allclose(
            sigma, sigma_ref, atol=1e-5
        )
        code = model.decoder.voxel_code(F)
        m1, s1 = decode_pairs(model.decoder, code, F, q[:1].expand(50, 3))
        assert torch.allclose(m1, mean_ref[:, 0], atol=1e-5)
        assert torch.allclose(s1, sigma_ref[:, 0], atol=1e-5)
