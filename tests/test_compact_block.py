"""Compact storage of submap encodings: rounding bounds, rank reduction, rotations."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mapping.compact_block import CompactBlock
from mapping.encoding import encode_points
from mapping.networks import load_default_prior
from mapping.voxel_block import VoxelBlock

V = 0.1
# unit round-off of the storage formats (relative rounding error of a normal number)
UNIT_ROUNDOFF = {"float16": 2.0**-11, "bfloat16": 2.0**-8, "float32": 2.0**-24}


@pytest.fixture(scope="module")
def block() -> VoxelBlock:
    rng = np.random.default_rng(0)
    d = rng.normal(size=(5000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    points = d * 0.3 + np.array([0.021, -0.13, 0.37])
    model = load_default_prior().eval()
    return encode_points(model, torch.from_numpy(points), torch.from_numpy(d), V)


@pytest.mark.parametrize("dtype", ["float16", "bfloat16", "float32"])
def test_full_rank_round_trip_is_within_storage_rounding(block, dtype) -> None:
    compact = CompactBlock.compress(block, 16, 16, dtype, jacobian_storage=dtype)
    back = compact.decompress()
    assert torch.equal(back.keys, block.keys) and torch.equal(back.weights, block.weights)
    u = UNIT_ROUNDOFF[dtype]
    for got, want in ((back.latents, block.latents), (back.jacobians, block.jacobians)):
        # each stored value is rounded once: |x~ - x| <= u |x| (+ the subnormal floor of float16)
        assert ((got - want).abs() <= u * want.abs() + 6e-8).all()


@pytest.mark.parametrize(("storage", "max_code"), [("int8", 127), ("int4", 7)])
def test_integer_jacobians_are_within_half_a_step(block, storage: str, max_code: int) -> None:
    compact = CompactBlock.compress(block, 16, 16, "float32", jacobian_storage=storage)
    assert compact.jacobian_coeffs.dtype == torch.int8
    assert int(compact.jacobian_coeffs.abs().max()) == max_code
    steps = compact.jacobian_scales  # identity basis at full rank: one step per channel
    err = (compact.decompress().jacobians - block.jacobians).abs()
    assert (err <= 0.5 * steps.view(1, -1, 1, 1) * (1 + 1e-5)).all()
    # the step is the channel's peak over the largest code: nothing saturates
    peak = block.jacobians.abs().amax(dim=(0, 2, 3))
    assert torch.allclose(steps, peak / max_code)


def test_int8_latents_are_within_half_a_step(block) -> None:
    compact = CompactBlock.compress(block, 16, 16, "int8")
    assert compact.latent_coeffs.dtype == torch.int8
    steps = compact.latent_scales  # identity basis at full rank: one step per channel
    err = (compact.decompress().latents - block.latents).abs()
    assert (err <= 0.5 * steps.view(1, -1, 1) * (1 + 1e-5)).all()
    assert torch.allclose(steps, block.latents.abs().amax(dim=(0, 2)) / 127)
    with pytest.raises(ValueError, match="latents cannot be stored as int4"):
        CompactBlock.compress(block, 16, 16, "int4")


def test_rank_reduction_keeps_the_leading_channel_energy(block) -> None:
    """The basis is the optimal one: the error is exactly the discarded eigenvalue energy."""
    J = block.jacobians.double()
    samples = J.permute(1, 0, 2, 3).reshape(16, -1)
    eigenvalues = torch.linalg.eigvalsh(samples @ samples.T).flip(0)
    for rank in (2, 4, 8):
        compact = CompactBlock.compress(block, 16, rank, "float32", jacobian_storage="float32")
        back = compact.decompress().jacobians.double()
        residual = float(((back - J) ** 2).sum())
        assert residual == pytest.approx(float(eigenvalues[rank:].sum()), rel=1e-3, abs=1e-9)
    # what the default keeps on a real encoding
    kept = float(eigenvalues[:4].sum() / eigenvalues.sum())
    assert kept > 0.99


def test_compression_commutes_with_rotation(block) -> None:
    """The basis acts on channels only: compress(rotate(b)) == rotate(compress(b))."""
    R = torch.as_tensor(Rotation.from_rotvec([0.3, -1.1, 0.5]).as_matrix(), dtype=torch.float32)

    def rotate(b: VoxelBlock) -> VoxelBlock:
        return VoxelBlock(
            b.keys, b.latents @ R.T, b.weights, torch.einsum("ia,mcab,jb->mcij", R, b.jacobians, R)
        )

    a = rotate(CompactBlock.compress(block, 4, 4, "float32", "float32").decompress())
    b = CompactBlock.compress(rotate(block), 4, 4, "float32", "float32").decompress()
    assert (a.latents - b.latents).abs().max() < 1e-5
    assert (a.jacobians - b.jacobians).abs().max() < 1e-4


def test_invalid_blocks_are_rejected(block) -> None:
    compact = CompactBlock.compress(block, 16, 4, "float16")
    with pytest.raises(ValueError, match="finite and positive"):
        dataclasses.replace(compact, weights=compact.weights * 0)
    with pytest.raises(ValueError, match="sorted and unique"):
        dataclasses.replace(compact, keys=compact.keys.flip(0))
    nan = compact.latent_coeffs.clone()
    nan[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        dataclasses.replace(compact, latent_coeffs=nan)
    huge = VoxelBlock(block.keys, block.latents * 1e6, block.weights, block.jacobians)
    with pytest.raises(ValueError, match="storage_dtype to float32"):
        CompactBlock.compress(huge, 16, 4, "float16")
    with pytest.raises(ValueError, match="no Jacobians"):
        CompactBlock.compress(block.without_jacobians(), 16, 4, "float16")
