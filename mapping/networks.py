"""Vector-neuron encoder (SO(3)-equivariant) and rotation-invariant SDF decoder.

Conventions: a latent is a ``(C, 3)`` tensor of C vector channels (rows). Rotating the scene by R
maps every channel ``f`` to ``R f``, i.e. the latent to ``F @ R.T``. Positions are in voxel units
(vu) relative to a voxel centre.

* :class:`PointEncoder` maps one point ``(r, n)`` to a ``(C, 3)`` latent with
  ``enc(r R^T, n R^T) = enc(r, n) R^T`` exactly (up to float error): it only uses VNLinear (no bias)
  and VN-LeakyReLU, whose projection rule commutes with rotations.
* :class:`Decoder` only sees rotation invariants of ``(F, q)``: the Gram matrix ``F F^T``, the
  projections ``F q`` and ``|q|^2``. Hence ``dec(F R^T, R q) = dec(F, q)`` exactly, which makes the
  SE(3) transform of a map exact up to the grid re-alignment.
"""

from __future__ import annotations

import hashlib
import io
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import nn

from common.atomic_io import write_bytes_atomic
from mapping.errors import WeightsFileError

_EPS = 1e-6


class VNLinear(nn.Module):
    """Channel mixing of vector features without bias: ``(..., C_in, 3) -> (..., C_out, 3)``."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(out_channels, in_channels))
        nn.init.kaiming_uniform_(self.weight, a=5**0.5)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.einsum("oi,...id->...od", self.weight, x)


class VNLeakyReLU(nn.Module):
    """Vector-neuron leaky ReLU (Deng et al. 2021).

    A learned direction ``k = U x`` per channel; where ``<x, k> < 0`` the component of ``x`` along
    ``k`` is removed. The leaky variant blends ``a x + (1 - a) relu(x)``.
    """

    def __init__(self, channels: int, negative_slope: float = 0.2) -> None:
        super().__init__()
        self.direction = VNLinear(channels, channels)
        self.negative_slope = negative_slope

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        k = self.direction(x)
        dot = (x * k).sum(-1, keepdim=True)
        k_sq = (k * k).sum(-1, keepdim=True)
        projected = x - (dot / (k_sq + _EPS)) * k
        relu = torch.where(dot >= 0, x, projected)
        return self.negative_slope * x + (1.0 - self.negative_slope) * relu


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of the prior (stored alongside the weights).

    Attributes:
        latent_channels: C, number of vector channels of a voxel latent.
        encoder_hidden: width of the two hidden VN layers of the point encoder.
        encoder_kind: ``"joint"`` feeds ``[r, n]`` as two vector channels into one VN branch (can
            express e.g. the plane offset ``r . n``); ``"two_branch"`` is the paper's design with
            separate position and normal branches of C/2 output channels each.
        decoder_hidden: width of the decoder MLP.
        decoder_layers: number of hidden layers of the decoder MLP.
        sdf_range_vu: the SDF mean is ``sdf_range_vu * tanh(.)``.
        sigma_min_vu: lower bound of the predicted standard deviation.
    """

    latent_channels: int = 16
    encoder_hidden: int = 32
    encoder_kind: str = "joint"
    decoder_hidden: int = 64
    decoder_layers: int = 3
    sdf_range_vu: float = 1.0
    sigma_min_vu: float = 0.01


def _vn_branch(in_channels: int, hidden: int, out_channels: int) -> nn.Sequential:
    return nn.Sequential(
        VNLinear(in_channels, hidden),
        VNLeakyReLU(hidden),
        VNLinear(hidden, hidden),
        VNLeakyReLU(hidden),
        VNLinear(hidden, out_channels),
    )


class PointEncoder(nn.Module):
    """Per-point SO(3)-equivariant encoder ``(r, n) -> (C, 3)``; a voxel latent is the mean."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.kind = cfg.encoder_kind
        if self.kind == "joint":
            self.branch = _vn_branch(2, cfg.encoder_hidden, cfg.latent_channels)
        elif self.kind == "two_branch":
            if cfg.latent_channels % 2:
                raise ValueError("two_branch encoder needs an even latent_channels")
            half = cfg.latent_channels // 2
            self.position = _vn_branch(1, cfg.encoder_hidden, half)
            self.normal = _vn_branch(1, cfg.encoder_hidden, half)
        else:
            raise ValueError(f"unknown encoder_kind '{self.kind}' (joint or two_branch)")

    def forward(self, r: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        """``r``, ``n``: ``(..., 3)`` position (vu, relative to the voxel centre), unit normal."""
        if self.kind == "joint":
            return self.branch(torch.stack([r, n], dim=-2))
        return torch.cat([self.position(r.unsqueeze(-2)), self.normal(n.unsqueeze(-2))], dim=-2)


def _triu_indices(c: int) -> tuple[torch.Tensor, torch.Tensor]:
    idx = torch.triu_indices(c, c)
    return idx[0], idx[1]


class Decoder(nn.Module):
    """Rotation-invariant decoder ``(F, q) -> (sdf mean [vu], sigma [vu])``.

    The first layer is split into a per-voxel part (Gram matrix, computed once per voxel by
    :meth:`voxel_code`) and a per-query part, so decoding many queries per voxel is cheap.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c = cfg.latent_channels
        rows, cols = _triu_indices(c)
        self.register_buffer("_rows", rows, persistent=False)
        self.register_buffer("_cols", cols, persistent=False)
        self.register_buffer("_upper", rows * c + cols, persistent=False)  # in the flat c x c
        h = cfg.decoder_hidden
        self.gram_in = nn.Linear(len(rows), h)
        self.query_in = nn.Linear(c + 1, h, bias=False)
        layers: list[nn.Module] = []
        for _ in range(cfg.decoder_layers - 1):
            layers += [nn.Softplus(beta=10.0), nn.Linear(h, h)]
        layers += [nn.Softplus(beta=10.0), nn.Linear(h, 2)]
        self.mlp = nn.Sequential(*layers)
        self.sdf_range_vu = cfg.sdf_range_vu
        self.sigma_min_vu = cfg.sigma_min_vu

    def voxel_code(self, F: torch.Tensor) -> torch.Tensor:
        """Per-voxel part of the first layer: ``(..., C, 3) -> (..., H)``."""
        gram = F @ F.transpose(-1, -2)
        return self.gram_in(gram.flatten(-2).index_select(-1, self._upper))

    def decode(
        self, code: torch.Tensor, F: torch.Tensor, q: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Decode queries ``q (..., Q, 3)`` of voxels with latents ``F (..., C, 3)``.

        ``code`` is ``voxel_code(F)`` with shape ``(..., H)``. Returns mean and sigma, ``(..., Q)``.
        """
        proj = q @ F.transpose(-1, -2)  # (..., Q, C)
        sq = (q * q).sum(-1, keepdim=True)
        x = code.unsqueeze(-2) + self.query_in(torch.cat([proj, sq], dim=-1))
        out = self.mlp(x)
        mean = self.sdf_range_vu * torch.tanh(out[..., 0])
        sigma = self.sigma_min_vu + nn.functional.softplus(out[..., 1])
        return mean, sigma

    def forward(self, F: torch.Tensor, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.decode(self.voxel_code(F), F, q)


class PriorModel(nn.Module):
    """Encoder + decoder with their architecture; the unit that is trained, shipped and loaded."""

    def __init__(self, cfg: ModelConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg or ModelConfig()
        self.encoder = PointEncoder(self.cfg)
        self.decoder = Decoder(self.cfg)

    @property
    def latent_channels(self) -> int:
        return self.cfg.latent_channels

    def identity(self) -> str:
        """Short hash of architecture and weights; map files store it to detect a mismatch."""
        digest = hashlib.sha256(repr(sorted(asdict(self.cfg).items())).encode())
        for name, tensor in sorted(self.state_dict().items()):
            digest.update(name.encode())
            digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
        return digest.hexdigest()[:16]

    def save(self, path: str | Path, metadata: dict | None = None) -> None:
        """Write ``{config, state_dict, metadata}``; loadable with ``weights_only=True``."""
        payload = {
            "format": "neural-remap-slam/prior",
            "version": 1,
            "config": asdict(self.cfg),
            "state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()},
            "metadata": metadata or {},
        }
        buffer = io.BytesIO()
        torch.save(payload, buffer)
        write_bytes_atomic(Path(path), buffer.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> PriorModel:
        """Load weights written by :meth:`save`. Never unpickles arbitrary objects."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(
                f"{path}: prior weights not found; run `python -m mapping.training.train`"
            )
        if not zipfile.is_zipfile(path):  # torch.save writes a zip archive
            raise WeightsFileError(
                f"{path}: not a prior weights file (not the zip archive torch.save writes: "
                "truncated, or another kind of file); re-create it with `python -m "
                "mapping.training.train` or set mapping.weights_path"
            ) from None
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
            if payload.get("format") != "neural-remap-slam/prior":
                raise ValueError("not a prior weights file")
            model = cls(ModelConfig(**payload["config"]))
            model.load_state_dict(payload["state_dict"])
        except Exception as exc:  # any corruption surfaces as one clear line
            raise WeightsFileError(
                f"{path}: not a valid prior weights file ({_weights_problem(exc)}); re-create it "
                "with `python -m mapping.training.train` or set mapping.weights_path"
            ) from None
        model.metadata = payload.get("metadata", {})
        return model


def _weights_problem(exc: Exception) -> str:
    """What is wrong with a weights file, without torch's advice to load it unsafely."""
    text = str(exc)
    if "weights_only" in text or "Weights only load failed" in text:
        return "it holds objects other than tensors, refused because loading them could run code"
    first = text.splitlines()[0] if text else ""
    return f"{exc.__class__.__name__}: {first[:120]}" if first else exc.__class__.__name__


DEFAULT_WEIGHTS = Path(__file__).parent / "weights" / "prior.pt"


def load_default_prior() -> PriorModel:
    """The shipped prior (``mapping/weights/prior.pt``).

    A missing file is an error, never a silent random model: a map made with untrained weights
    looks plausible and is wrong. Untrained weights are for experiments only and must be asked
    for explicitly (``PriorModel()`` after ``torch.manual_seed``).
    """
    if not DEFAULT_WEIGHTS.is_file():
        raise FileNotFoundError(
            f"{DEFAULT_WEIGHTS}: the shipped prior weights are missing from this installation; "
            "reinstall the package (`pip install -e .`), set mapping.weights_path, or re-create "
            "them with `python -m mapping.training.train --config configs/train_prior.yaml "
            "--export "
            f"{DEFAULT_WEIGHTS}`"
        )
    return PriorModel.load(DEFAULT_WEIGHTS)
