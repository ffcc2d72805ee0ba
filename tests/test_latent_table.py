"""The encoder's latent table against the exact span encoder (mapping/latent_table.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mapping.analytic_prior import planar_prior
from mapping.config import MapConfig
from mapping.encoding import encode_points
from mapping.latent_table import LatentTable, latent_table
from mapping.networks import PriorModel, load_default_prior
from mapping.span_encoder import point_latents

torch.set_num_threads(1)
V = 0.1


def _pairs(count: int, seed: int = 0, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Random pairs as encoding makes them: r in [-1, 1]^3, unit normals."""
    g = torch.Generator().manual_seed(seed)
    r = torch.rand(count, 3, generator=g, dtype=torch.float64) * 2.0 - 1.0
    n = torch.randn(count, 3, generator=g, dtype=torch.float64)
    return r.to(dtype), (n / n.norm(dim=1, keepdim=True)).to(dtype)


def _relative(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a - b).flatten(1).norm(dim=1) / b.flatten(1).norm(dim=1).clamp_min(1e-12)


def _sphere(count: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(count, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return torch.from_numpy(0.4 * d + [0.03, 0.41, -0.2]), torch.from_numpy(d)


def test_planar_prior_is_reproduced_exactly() -> None:
    """The tangent-plane prior's latent is linear in r (channels r and n), which bilinear
    interpolation reproduces: latents and Jacobians equal the network's to float rounding."""
    model = planar_prior().double()
    r, n = _pairs(5000, dtype=torch.float64)
    F, dF = point_latents(model.encoder, r, n, True)
    F_table, dF_table = LatentTable.build(model.encoder, 16).latents(r, n, True)
    assert torch.allclose(F_table, F, rtol=0, atol=1e-10)
    assert torch.allclose(dF_table, dF, rtol=0, atol=1e-10)
    assert dF.abs().max() > 0.5  # the Jacobian is not trivially zero


@pytest.mark.parametrize("prior", ["shipped", "random"])
def test_table_matches_the_network(prior: str) -> None:
    """Per pair the lookup (latents and Jacobians: the Jacobian's assembly from the
    interpolated partials) is the network to interpolation error, which shrinks ~4x per
    doubling of the nodes (second order); per voxel (means of pairs) it is ~1e-5, and at most
    ~1 % in a voxel of few pairs that all lie where the network turns sharply."""
    torch.manual_seed(3)
    model = load_default_prior() if prior == "shipped" else PriorModel().eval()
    model = model.double()
    r, n = _pairs(20000, dtype=torch.float64)
    F, dF = point_latents(model.encoder, r, n, True)
    latent_medians, jacobian_medians = [], []
    for nodes in (64, 128):
        F_table, dF_table = LatentTable.build(model.encoder, nodes).latents(r, n, True)
        latent_medians.append(float(_relative(F_table, F).median()))
        jacobian_medians.append(float(_relative(dF_table, dF).median()))
    assert latent_medians[1] < 1e-3 and latent_medians[1] < latent_medians[0] / 2.5
    assert jacobian_medians[1] < 1e-2 and jacobian_medians[1] < jacobian_medians[0] / 2.5

    points, normals = _sphere(3000)
    exact = encode_points(model, points, normals, V)
    looked_up = encode_points(model, points, normals, V, table_nodes=256)
    assert torch.equal(looked_up.keys, exact.keys) and torch.equal(looked_up.weights, exact.weights)
    latent_error = _relative(looked_up.latents, exact.latents)
    assert float(latent_error.median()) < 1e-4 and float(latent_error.max()) < 2e-2
    assert float(_relative(looked_up.jacobians, exact.jacobians).median()) < 1e-2


def test_table_encoding_is_rotation_equivariant() -> None:
    """The table holds invariants: rotating the points and normals rotates every voxel latent
    (for a rotation that maps the voxel grid onto itself, so the voxels are the same)."""
    model = load_default_prior()
    points, normals = _sphere(2000, seed=2)
    R = torch.from_numpy(Rotation.from_euler("z", 90, degrees=True).as_matrix())
    a = encode_points(model, points, normals, V, table_nodes=256)
    b = encode_points(model, points @ R.T, normals @ R.T, V, table_nodes=256)
    keys_rotated = (a.keys.double() + 0.5) @ R.T - 0.5
    order_a = torch.argsort(_key_order(keys_rotated.round().long()))
    order_b = torch.argsort(_key_order(b.keys))
    assert torch.equal(keys_rotated.round().long()[order_a], b.keys[order_b])
    expected = a.latents.double() @ R.T
    assert torch.allclose(b.latents[order_b].double(), expected[order_a], rtol=0, atol=1e-5)


def _key_order(keys: torch.Tensor) -> torch.Tensor:
    return (keys[:, 0] * 4096 + keys[:, 1]) * 4096 + keys[:, 2]


def test_table_needs_unit_normals() -> None:
    model = load_default_prior()
    points, normals = _sphere(100)
    with pytest.raises(ValueError, match="unit length"):
        encode_points(model, points, 1.01 * normals, V, table_nodes=32)


def test_table_follows_the_weights() -> None:
    """The cached table is rebuilt when the encoder's weights change in place (training)."""
    torch.manual_seed(0)
    model = PriorModel().eval()
    first = latent_table(model.encoder, 16)
    assert latent_table(model.encoder, 16) is first
    with torch.no_grad():
        next(model.encoder.parameters()).mul_(1.5)
    second = latent_table(model.encoder, 16)
    assert second is not first and not torch.allclose(second.values, first.values)


def test_config_rejects_a_one_node_table() -> None:
    with pytest.raises(ValueError, match="encoder_table_nodes"):
        MapConfig(encoder_table_nodes=1)
