"""Compact long-term storage of a submap's encoding (docs/design.md §3.1, §3.7).

A submap keeps its original encoding for life, so that encoding is where the map's bytes go. A
:class:`CompactBlock` holds it as

* packed int64 keys (sorted) and float32 weights (point counts, exact integers),
* latents as coefficients on a per-block *channel basis*, in half precision (or quantised to
  int8 with one step per basis direction, ``max|a_k| / 127``, where the map file must be small),
* Jacobians as coefficients on their own channel basis, quantised to int8 with one step per
  basis direction (or to int4, codes within +-7 held one per byte, or in a float format). They
  only feed the transform's first-order term, whose effect on the mesh is a fraction of a
  millimetre; the int8 rounding (at most half a step, ``max|b_k| / 254``) changes the two-path
  transform benchmark by less than its noise, int4's makes its mean distances 10-16 % larger.

The channel basis is the leading eigenvectors of the (uncentred) channel second-moment matrix of
the block: ``F[m, :, d] ~ B_F @ a[m, :, d]`` and ``J[m, :, i, j] ~ B_J @ b[m, :, i, j]``. The basis
acts on the channel index only, so it commutes with rotations (``F R^T`` and ``R J R^T`` act on the
spatial indices): a compressed block transforms exactly like the block it approximates. With a
rank equal to the number of channels the basis is the identity and only the half-precision
rounding remains.

Why the ranks can be low: the vector-neuron encoder maps the two input vectors ``[r, n]`` of a point
to channels that all lie in ``span(r, n)``, so the voxel means (and their derivatives) concentrate
in a few channel directions; measured on the demo room, 4 of 16 Jacobian directions hold 99.7 % of
the energy (``benchmarks/bench_map_size.py`` reports the transform-fidelity effect of each rank).

Everything decompresses to a float32 :class:`~mapping.voxel_block.VoxelBlock`; all arithmetic on
blocks (transform, fuse, remove, decode) stays float32.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from common.voxel_keys import unpack_keys
from mapping.voxel_block import VoxelBlock

StorageDtype = Literal["int8", "float16", "bfloat16", "float32"]
JacobianStorage = Literal["int4", "int8", "float16", "bfloat16", "float32"]
_DTYPES: dict[str, torch.dtype] = {
    "int4": torch.int8,  # codes within +-7, held one per byte
    "int8": torch.int8,
    "float16": torch.float16,
    "bfloat16": torch.bfloat16,
    "float32": torch.float32,
}
_MAX_CODES = {"int4": 7, "int8": 127}
"""Largest code magnitude of each integer storage."""


def storage_dtype(name: str) -> torch.dtype:
    """The torch dtype of a storage dtype name (one-line error for an unknown one)."""
    if name not in _DTYPES:
        raise ValueError(f"unknown storage dtype '{name}' (one of {', '.join(_DTYPES)})")
    return _DTYPES[name]


def channel_basis(samples: torch.Tensor, rank: int) -> torch.Tensor:
    """``(C, k)`` orthonormal basis of the ``rank`` leading channel directions of ``samples``.

    ``samples`` is ``(C, S)``: channel vectors as columns. Uncentred on purpose: subtracting a mean
    would not commute with rotations. A rank of ``C`` or more gives the identity.
    """
    channels = samples.shape[0]
    if rank >= channels or samples.shape[1] == 0:
        return torch.eye(channels, min(rank, channels), device=samples.device)
    x = samples.to(torch.float64)
    _, vectors = torch.linalg.eigh(x @ x.T)
    basis = vectors[:, -rank:].flip(1)  # leading first
    # a deterministic sign per direction (eigh's sign is arbitrary)
    signs = torch.sign(basis[basis.abs().argmax(0), torch.arange(rank, device=basis.device)])
    return (basis * signs).to(torch.float32)


def _quantise(x: torch.Tensor, max_code: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(M, k, ...)`` -> int8 codes within ``+-max_code`` and ``(k,)`` float32 scales (one per
    basis direction, its peak over ``max_code``), ``x ~ codes * scale``."""
    shape = (1, -1) + (1,) * (x.dim() - 2)
    others = [d for d in range(x.dim()) if d != 1]
    peak = x.abs().amax(dim=others) if x.shape[0] else torch.zeros(x.shape[1], device=x.device)
    scales = torch.where(peak > 0, peak / max_code, torch.ones_like(peak)).to(torch.float32)
    codes = torch.round(x / scales.view(shape)).clamp_(-max_code, max_code)
    return codes.to(torch.int8), scales


def _store(x: torch.Tensor, storage: str, what: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Coefficients ``x`` (``(M, k, ...)``) as ``storage`` codes and their ``(k,)`` scales
    (ones for a float format)."""
    if storage in _MAX_CODES:
        return _quantise(x, _MAX_CODES[storage])
    ones = torch.ones(x.shape[1], dtype=torch.float32, device=x.device)
    return _to_storage(x, storage_dtype(storage), what), ones


def _to_storage(x: torch.Tensor, dtype: torch.dtype, what: str) -> torch.Tensor:
    stored = x.to(dtype)
    if not bool(torch.isfinite(stored).all()):
        raise ValueError(
            f"{what} do not fit {dtype} storage (non-finite after rounding); "
            "set mapping.storage_dtype to float32"
        )
    return stored


@dataclass(frozen=True)
class CompactBlock:
    """A :class:`VoxelBlock` with packed keys and rank-reduced, half-precision channels.

    Attributes:
        keys: ``(M,)`` packed int64 keys, sorted and unique.
        weights: ``(M,)`` float32 positive weights.
        latent_basis: ``(C, kF)`` float32 orthonormal channel basis of the latents.
        latent_coeffs: ``(M, kF, 3)`` coefficients: int8 codes or a float format.
        jacobian_basis: ``(C, kJ)`` float32 orthonormal channel basis of the Jacobians.
        jacobian_coeffs: ``(M, kJ, 3, 3)`` coefficients: int8 codes (within +-7 for ``int4``)
            or a float format.
        jacobian_scales: ``(kJ,)`` float32 step of each direction's integer codes (1 for floats).
        latent_scales: ``(kF,)`` float32 step of each direction's integer codes (1 for floats).
    """

    keys: torch.Tensor
    weights: torch.Tensor
    latent_basis: torch.Tensor
    latent_coeffs: torch.Tensor
    jacobian_basis: torch.Tensor
    jacobian_coeffs: torch.Tensor
    jacobian_scales: torch.Tensor
    latent_scales: torch.Tensor

    def __post_init__(self) -> None:
        m = self.keys.shape[0]
        c, k_f = self.latent_basis.shape
        k_j = self.jacobian_basis.shape[1]
        shapes_ok = (
            self.keys.dtype == torch.int64
            and self.keys.shape == (m,)
            and self.weights.shape == (m,)
            and self.latent_coeffs.shape == (m, k_f, 3)
            and self.jacobian_basis.shape == (c, k_j)
            and self.jacobian_coeffs.shape == (m, k_j, 3, 3)
            and self.jacobian_scales.shape == (k_j,)
            and self.latent_scales.shape == (k_f,)
        )
        if not shapes_ok:
            raise ValueError(
                "CompactBlock: inconsistent shapes (keys "
                f"{tuple(self.keys.shape)}, weights {tuple(self.weights.shape)}, latents "
                f"{tuple(self.latent_coeffs.shape)} on basis {tuple(self.latent_basis.shape)}, "
                f"jacobians {tuple(self.jacobian_coeffs.shape)} on basis "
                f"{tuple(self.jacobian_basis.shape)})"
            )
        if m and not bool((self.weights > 0).all() and torch.isfinite(self.weights).all()):
            raise ValueError("CompactBlock: weights must be finite and positive")
        if m > 1 and not bool((self.keys[1:] > self.keys[:-1]).all()):
            raise ValueError("CompactBlock: keys must be sorted and unique")
        for name in ("jacobian_scales", "latent_scales"):
            if not bool((getattr(self, name) > 0).all()):
                raise ValueError(f"CompactBlock: {name} must be positive")
        for name in _FLOAT_FIELDS:
            values = getattr(self, name)
            if values.is_floating_point() and not bool(torch.isfinite(values).all()):
                raise ValueError(f"CompactBlock: {name} holds NaN or infinite values")

    @classmethod
    def compress(
        cls,
        block: VoxelBlock,
        latent_rank: int,
        jacobian_rank: int,
        dtype: StorageDtype,
        jacobian_storage: JacobianStorage = "int8",
    ) -> CompactBlock:
        """Compress a block that has Jacobians (keys sorted and unique, as encoders return)."""
        if block.jacobians is None:
            raise ValueError("CompactBlock.compress: the block has no Jacobians to keep")
        m, c = block.num_voxels, block.channels
        latents = block.latents  # (M, C, 3)
        jacobians = block.jacobians  # (M, C, 3, 3)
        b_f = channel_basis(latents.permute(1, 0, 2).reshape(c, -1), latent_rank)
        b_j = channel_basis(jacobians.permute(1, 0, 2, 3).reshape(c, -1), jacobian_rank)
        a = torch.einsum("ck,mcd->mkd", b_f, latents)
        b = torch.einsum("ck,mcij->mkij", b_j, jacobians)
        keys = block.packed_keys()
        if m > 1 and not bool((keys[1:] > keys[:-1]).all()):
            raise ValueError("CompactBlock.compress: block keys must be sorted and unique")
        if dtype == "int4":
            raise ValueError("latents cannot be stored as int4 (int8 or a float format)")
        latent_coeffs, latent_scales = _store(a, dtype, "latents")
        jacobian_coeffs, jacobian_scales = _store(b, jacobian_storage, "Jacobians")
        return cls(
            keys=keys,
            weights=block.weights.to(torch.float32),
            latent_basis=b_f,
            latent_coeffs=latent_coeffs,
            jacobian_basis=b_j,
            jacobian_coeffs=jacobian_coeffs,
            jacobian_scales=jacobian_scales,
            latent_scales=latent_scales,
        )

    def decompress(self, with_jacobians: bool = True) -> VoxelBlock:
        """The float32 block (deterministic: the same bytes always give the same block)."""
        basis = self.latent_basis * self.latent_scales  # scales fold into the basis
        latents = torch.einsum("ck,mkd->mcd", basis, self.latent_coeffs.float())
        jacobians = None
        if with_jacobians:
            basis = self.jacobian_basis * self.jacobian_scales  # scales fold into the basis
            jacobians = torch.einsum("ck,mkij->mcij", basis, self.jacobian_coeffs.float())
        return VoxelBlock(unpack_keys(self.keys), latents, self.weights, jacobians)

    @property
    def num_voxels(self) -> int:
        return int(self.keys.shape[0])

    @property
    def channels(self) -> int:
        return int(self.latent_basis.shape[0])

    @property
    def device(self) -> torch.device:
        return self.keys.device

    def to(self, device: torch.device | str) -> CompactBlock:
        return CompactBlock(*(getattr(self, f).to(device) for f in FIELDS))

    def centers(self, voxel_size_m: float) -> np.ndarray:
        """``(M, 3)`` float64 world coordinates of the voxel centres."""
        return (unpack_keys(self.keys).cpu().numpy().astype(np.float64) + 0.5) * voxel_size_m

    def nbytes(self) -> int:
        """Bytes held by the arrays (what the block costs in memory)."""
        return sum(getattr(self, f).element_size() * getattr(self, f).numel() for f in FIELDS)


FIELDS = (
    "keys",
    "weights",
    "latent_basis",
    "latent_coeffs",
    "jacobian_basis",
    "jacobian_coeffs",
    "jacobian_scales",
    "latent_scales",
)
_FLOAT_FIELDS = FIELDS[2:]  # int8 codes are skipped by the finiteness check
