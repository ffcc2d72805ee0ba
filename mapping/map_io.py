"""Saving and loading a neural map with its submaps (DESIGN 5.7).

Format ``neural-remap-slam/map`` version 1: one uncompressed ``.npz`` (numpy zip) written with
``allow_pickle=False`` and read with ``allow_pickle=False``, so loading never executes code.

* ``header``: a 0-d unicode array holding JSON: format, version, voxel size, the map config, the
  model identity (:meth:`PriorModel.identity`) and latent channels, the number of submaps and, per
  submap, its id, whether it is fused and whether its ``placed`` block is stored separately.
* ``map_keys (M,3) int64``, ``map_latents (M,C,3) float32``, ``map_weights (M,) float64``,
  ``map_jacobians (M,C,3,3) float32``: the global map (float64 weights as held in memory).
* per submap ``i``: ``s{i}_T_W_A_encoded``, ``s{i}_T_W_A`` (4x4 float64) and the blocks
  ``s{i}_original_*`` and, when it is not the original, ``s{i}_placed_*`` (keys, latents, weights,
  jacobians).

Files are written to a temporary file in the target folder and moved into place.
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from mapping.config import MapConfig
from mapping.errors import MapFileError
from mapping.networks import PriorModel
from mapping.voxel_block import VoxelBlock

if TYPE_CHECKING:
    from mapping.neural_map import NeuralMap, Submap

FORMAT = "neural-remap-slam/map"
VERSION = 1
_BLOCK_FIELDS = ("keys", "latents", "weights", "jacobians")


def _block_arrays(prefix: str, block: VoxelBlock) -> dict[str, np.ndarray]:
    return {
        f"{prefix}_{name}": getattr(block, name).detach().cpu().numpy() for name in _BLOCK_FIELDS
    }


def _read_block(data: dict[str, np.ndarray], prefix: str, device: torch.device) -> VoxelBlock:
    return VoxelBlock(*(torch.from_numpy(data[f"{prefix}_{name}"]) for name in _BLOCK_FIELDS)).to(
        device
    )


def save_map(neural_map: NeuralMap, path: str | Path, submaps: list[Submap]) -> None:
    """Write ``neural_map`` and ``submaps`` to ``path`` atomically."""
    path = Path(path)
    ids = [s.submap_id for s in submaps]
    if len(set(ids)) != len(ids):
        raise ValueError("save: submap ids must be unique")
    block = neural_map.voxel_block()
    arrays = _block_arrays("map", block)
    arrays["map_weights"] = neural_map._weights64().cpu().numpy()
    records = []
    for i, s in enumerate(submaps):
        separate = s.placed is not s.original
        records.append({"id": int(s.submap_id), "fused": bool(s.fused), "placed_stored": separate})
        arrays[f"s{i}_T_W_A_encoded"] = np.asarray(s.T_W_A_encoded, dtype=np.float64)
        arrays[f"s{i}_T_W_A"] = np.asarray(s.T_W_A, dtype=np.float64)
        arrays.update(_block_arrays(f"s{i}_original", s.original))
        if separate:
            arrays.update(_block_arrays(f"s{i}_placed", s.placed))
    header = {
        "format": FORMAT,
        "version": VERSION,
        "voxel_size_m": neural_map.voxel_size_m,
        "config": neural_map.cfg.model_dump(),
        "model_identity": neural_map.model.identity(),
        "latent_channels": neural_map.model.latent_channels,
        "num_voxels": block.num_voxels,
        "submaps": records,
    }
    arrays["header"] = np.array(json.dumps(header))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise MapFileError(f"{path}: map file not found; check the path")
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise MapFileError(
            f"{path}: not a readable neural map file (truncated or foreign: "
            f"{exc.__class__.__name__}); re-save the map with NeuralMap.save"
        ) from exc


def _header(path: Path, data: dict[str, np.ndarray]) -> dict:
    if "header" not in data:
        raise MapFileError(f"{path}: no map header; this is not a {FORMAT} file")
    try:
        header = json.loads(str(data["header"]))
    except (json.JSONDecodeError, TypeError) as exc:
        raise MapFileError(f"{path}: corrupt map header; re-save the map") from exc
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise MapFileError(f"{path}: not a {FORMAT} file")
    if header.get("version") != VERSION:
        raise MapFileError(
            f"{path}: map format version {header.get('version')} is not supported "
            f"(this code reads version {VERSION}); re-create the map with this version"
        )
    return header


def load_map(
    cls: type[NeuralMap], path: str | Path, model: PriorModel | None
) -> tuple[NeuralMap, list[Submap]]:
    """Read a map written by :func:`save_map`; any problem is a one-line :class:`MapFileError`."""
    from mapping.neural_map import Submap

    path = Path(path)
    data = _read_npz(path)
    header = _header(path, data)
    try:
        cfg = MapConfig(**header["config"])
    except Exception as exc:
        raise MapFileError(
            f"{path}: invalid map config in header ({exc.__class__.__name__})"
        ) from exc
    neural_map = cls(cfg, model)
    identity = neural_map.model.identity()
    if header.get("model_identity") != identity:
        raise MapFileError(
            f"{path}: map was encoded with model {header.get('model_identity')} but the loaded "
            f"model is {identity}; load it with the same prior weights (mapping.weights_path)"
        )
    device = neural_map.device
    try:
        block = _read_block(data, "map", device)
        weights64 = torch.from_numpy(data["map_weights"]).to(torch.float64)
        submaps = []
        for i, rec in enumerate(header["submaps"]):
            original = _read_block(data, f"s{i}_original", device)
            placed = _read_block(data, f"s{i}_placed", device) if rec["placed_stored"] else original
            submaps.append(
                Submap(
                    submap_id=int(rec["id"]),
                    T_W_A_encoded=data[f"s{i}_T_W_A_encoded"].astype(np.float64),
                    original=original,
                    T_W_A=data[f"s{i}_T_W_A"].astype(np.float64),
                    placed=placed,
                    fused=bool(rec["fused"]),
                )
            )
    except (KeyError, ValueError, TypeError, RuntimeError) as exc:
        raise MapFileError(
            f"{path}: map file content is inconsistent ({exc.__class__.__name__}: "
            f"{str(exc).splitlines()[0] if str(exc) else ''}); re-save the map"
        ) from exc
    if block.channels != neural_map.model.latent_channels:
        raise MapFileError(f"{path}: latent size does not match the model")
    neural_map._restore(block, weights64, {s.submap_id for s in submaps if s.fused})
    return neural_map, submaps
