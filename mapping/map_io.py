"""Saving and loading a neural map with its submaps (docs/design.md §3.7).

Format ``neural-remap-slam/map`` version 2: one compressed ``.npz`` (numpy zip, deflate) written
and read with ``allow_pickle=False``, so loading never executes code. It holds what cannot be
derived: every submap's compact original encoding (:class:`~mapping.compact_block.CompactBlock`)
and its poses. The global map is not stored: it is the fusion of the fused submaps' placed blocks,
rebuilt on load (equal to the saved one up to float32 rounding of the fusion order).

* ``header``: a 0-d unicode array holding JSON: format, version, voxel size, the map config, the
  model identity (:meth:`PriorModel.identity`), latent channels, storage dtype, submap count.
* per submap (``S`` of them, in order): ``submap_ids (S,) int64``, ``submap_fused (S,) bool``,
  ``submap_T_W_A_encoded (S,4,4)`` and ``submap_T_W_A (S,4,4)`` float64, ``submap_offsets (S+1,)
  int64`` (rows of submap ``i`` are ``offsets[i]:offsets[i+1]`` in the voxel arrays),
  ``latent_basis (S,C,kF)``, ``jacobian_basis (S,C,kJ)`` and ``jacobian_scales (S,kJ)`` float32.
* per voxel of every submap: ``keys`` (packed int64, see :mod:`mapping.voxel_block`),
  ``weights`` float32, ``latent_coeffs (N,kF,3)`` in the header's ``storage_dtype`` and
  ``jacobian_coeffs (N,kJ,3,3)`` in its ``jacobian_storage`` (``int8``, ``float16`` and
  ``float32`` as numpy types; ``bfloat16`` as its raw ``int16`` bits). A submap's latents are
  ``latent_basis[i] @ latent_coeffs[rows]`` (channels x 3 per voxel), its Jacobians
  ``(jacobian_basis[i] * jacobian_scales[i]) @ jacobian_coeffs[rows]``.

Version 3 adds an optional *session* section (docs/design.md §4): ``header["session"]`` (JSON)
and arrays named ``session_*``, written and read opaquely here (the SLAM layer defines them; see
``slam.algorithm.merge.session``). Version 4 changes only that section (frames'
anchor-relative poses as float32 quaternion and translation instead of float64 matrices).
Version 2 and 3 files still load as maps; :func:`load_session` reads only the current version's
section and refuses theirs.

Files are written to a temporary file in the target folder and moved into place. The per-voxel
arrays are written submap by submap (:class:`_Stacked`): the file is the one ``np.savez_compressed``
writes of their concatenation, without the concatenation in memory (that copy of every submap's
encoding used to set a run's peak RSS).
"""

from __future__ import annotations

import json
import zipfile
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from common.atomic_io import atomic_path
from mapping.compact_block import CompactBlock, storage_dtype
from mapping.config import MapConfig
from mapping.errors import MapFileError
from mapping.networks import PriorModel
from mapping.neural_map import NeuralMap, Submap
from mapping.transform import check_rigid

FORMAT = "neural-remap-slam/map"
VERSION = 4
READABLE_VERSIONS = (2, 3, 4)
SESSION_PREFIX = "session_"
_PER_VOXEL = ("keys", "weights", "latent_coeffs", "jacobian_coeffs")
_PER_SUBMAP = ("latent_basis", "jacobian_basis", "jacobian_scales")


def _to_numpy(t: torch.Tensor) -> np.ndarray:
    t = t.detach().cpu()
    if t.dtype == torch.bfloat16:  # numpy has no bfloat16: keep the raw bits
        t = t.view(torch.int16)
    return t.numpy()


def _from_numpy(a: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
    t = torch.from_numpy(np.ascontiguousarray(a))
    if dtype == torch.bfloat16:
        if t.dtype != torch.int16:
            raise ValueError(f"bfloat16 coefficients must be stored as int16, got {t.dtype}")
        return t.view(torch.bfloat16)
    if t.dtype != dtype:
        raise ValueError(f"coefficients are {t.dtype}, the header says {dtype}")
    return t


class _Stacked(NamedTuple):
    """An array stored as the concatenation of ``parts`` along the first axis (never built)."""

    parts: list[np.ndarray]


def _write_stacked(fid, parts: list[np.ndarray]) -> None:
    """The ``.npy`` bytes ``np.lib.format.write_array`` writes of ``np.concatenate(parts)``: the
    same header (dtype promoted as ``concatenate`` does, C order), then each part's data."""
    dtype = np.result_type(*parts)
    tail = parts[0].shape[1:]
    if any(p.shape[1:] != tail for p in parts):
        raise ValueError(f"save: parts of shapes {[p.shape for p in parts]} do not stack")
    header = np.lib.format.header_data_from_array_1_0(np.empty((0, *tail), dtype))
    header["shape"] = (sum(p.shape[0] for p in parts), *tail)
    np.lib.format.write_array_header_1_0(fid, header)
    for part in parts:
        if part.size:
            fid.write(memoryview(np.ascontiguousarray(part, dtype=dtype)).cast("B"))


def _write_npz(f, arrays: dict[str, np.ndarray | _Stacked]) -> None:
    """``np.savez_compressed(f, **arrays)`` (the same entries in the same order, each written
    as ``np.save`` would), where a :class:`_Stacked` entry is written part by part."""
    with zipfile.ZipFile(f, mode="w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as zipf:
        for name, value in arrays.items():
            with zipf.open(f"{name}.npy", "w", force_zip64=True) as fid:  # zip64 as numpy does
                if isinstance(value, _Stacked):
                    _write_stacked(fid, value.parts)
                else:
                    np.lib.format.write_array(fid, np.asanyarray(value), allow_pickle=False)


def save_map(
    neural_map: NeuralMap,
    path: str | Path,
    submaps: list[Submap],
    session: tuple[dict, dict[str, np.ndarray]] | None = None,
) -> None:
    """Write ``submaps`` with ``neural_map``'s config and model identity to ``path``, atomically.

    ``session``: ``(header, arrays)`` of the run's session section, stored as given.
    """
    path = Path(path)
    ids = [s.submap_id for s in submaps]
    if len(set(ids)) != len(ids):
        raise ValueError("save: submap ids must be unique")
    if {s.submap_id for s in submaps if s.fused} != neural_map.fused_ids:
        raise ValueError("save: the submaps passed must include exactly the map's fused submaps")
    cfg = neural_map.cfg
    channels = neural_map.model.latent_channels
    dtype = storage_dtype(cfg.storage_dtype)
    jac_dtype = storage_dtype(cfg.jacobian_storage)
    originals = [s.original for s in submaps]
    if any(
        o.latent_coeffs.dtype != dtype or o.jacobian_coeffs.dtype != jac_dtype for o in originals
    ):
        raise ValueError(
            f"save: every submap must be stored as this map's {cfg.storage_dtype} latents and "
            f"{cfg.jacobian_storage} Jacobians"
        )
    counts = [o.num_voxels for o in originals]
    arrays: dict[str, np.ndarray | _Stacked] = {
        "submap_ids": np.asarray(ids, dtype=np.int64),
        "submap_fused": np.asarray([s.fused for s in submaps], dtype=bool),
        "submap_T_W_A_encoded": np.asarray(
            [s.T_W_A_encoded for s in submaps], dtype=np.float64
        ).reshape(-1, 4, 4),
        "submap_T_W_A": np.asarray([s.T_W_A for s in submaps], dtype=np.float64).reshape(-1, 4, 4),
        "submap_offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
    }
    k_f, k_j = min(cfg.latent_rank, channels), min(cfg.jacobian_rank, channels)
    shapes = {
        "latent_basis": (channels, k_f),
        "jacobian_basis": (channels, k_j),
        "jacobian_scales": (k_j,),
    }
    for name, shape in shapes.items():
        if any(tuple(getattr(o, name).shape) != shape for o in originals):
            raise ValueError(f"save: every submap's {name} must be {shape}")
        arrays[name] = np.zeros((len(originals), *shape), np.float32)
        for i, o in enumerate(originals):
            arrays[name][i] = _to_numpy(getattr(o, name))
    empty = {  # zero-row templates keep shapes and dtypes when there are no voxels at all
        "keys": np.zeros(0, np.int64),
        "weights": np.zeros(0, np.float32),
        "latent_coeffs": _to_numpy(torch.zeros(0, k_f, 3, dtype=dtype)),
        "jacobian_coeffs": _to_numpy(torch.zeros(0, k_j, 3, 3, dtype=jac_dtype)),
    }
    for name in _PER_VOXEL:  # views of the submaps' tensors, written one after the other
        arrays[name] = _Stacked([empty[name], *(_to_numpy(getattr(o, name)) for o in originals)])
    header = {
        "format": FORMAT,
        "version": VERSION,
        "voxel_size_m": neural_map.voxel_size_m,
        "config": neural_map.cfg.model_dump(),
        "model_identity": neural_map.model.identity(),
        "latent_channels": channels,
        "storage_dtype": cfg.storage_dtype,
        "jacobian_storage": cfg.jacobian_storage,
        "num_submaps": len(submaps),
    }
    if session is not None:
        header["session"] = session[0]
        for name, value in session[1].items():
            arrays[SESSION_PREFIX + name] = np.asarray(value)
    arrays["header"] = np.array(json.dumps(header))
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        _write_npz(f, arrays)


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise MapFileError(f"{path}: map file not found; check the path")
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError) as exc:
        raise MapFileError(
            f"{path}: not a readable neural map file (truncated or foreign: "
            f"{exc.__class__.__name__}); write it again with slam.run"
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
    if header.get("version") not in READABLE_VERSIONS:
        raise MapFileError(
            f"{path}: map format version {header.get('version')} is not supported (this code "
            f"reads versions {READABLE_VERSIONS}); regenerate it by running `python -m slam.run` "
            "on the sequence again"
        )
    return header


def load_map(
    path: str | Path, model: PriorModel | None = None
) -> tuple[NeuralMap, list[Submap]]:
    """Read a map written by :func:`save_map`; any problem is a one-line :class:`MapFileError`.

    The global map is rebuilt by fusing the fused submaps in the order they are stored.
    """
    path = Path(path)
    data = _read_npz(path)
    header = _header(path, data)
    try:
        cfg = MapConfig(**header["config"])
    except Exception as exc:
        raise MapFileError(
            f"{path}: invalid map config in header ({exc.__class__.__name__})"
        ) from exc
    neural_map = NeuralMap(cfg, model)
    identity = neural_map.model.identity()
    if header.get("model_identity") != identity:
        raise MapFileError(
            f"{path}: map was encoded with model {header.get('model_identity')} but the loaded "
            f"model is {identity}; load it with the same prior weights (mapping.weights_path)"
        )
    if header.get("latent_channels") != neural_map.model.latent_channels:
        raise MapFileError(f"{path}: latent size does not match the model")
    device = neural_map.device
    try:
        dtype = storage_dtype(header["storage_dtype"])
        jac_dtype = storage_dtype(header["jacobian_storage"])
        offsets = data["submap_offsets"]
        n_sub = int(header["num_submaps"])
        ids = data["submap_ids"]
        if offsets.shape != (n_sub + 1,) or offsets[0] != 0 or np.any(np.diff(offsets) < 0):
            raise ValueError("submap offsets are not a monotone (S+1,) array starting at 0")
        if offsets[-1] != data["keys"].shape[0] or len(set(ids.tolist())) != n_sub:
            raise ValueError("submap offsets, ids and voxel arrays disagree")
        voxel = {
            "keys": torch.from_numpy(data["keys"].astype(np.int64, copy=False)),
            "weights": torch.from_numpy(data["weights"]).to(torch.float32),
            "latent_coeffs": _from_numpy(data["latent_coeffs"], dtype),
            "jacobian_coeffs": _from_numpy(data["jacobian_coeffs"], jac_dtype),
        }
        submaps = []
        for i in range(n_sub):
            rows = slice(int(offsets[i]), int(offsets[i + 1]))
            original = CompactBlock(
                keys=voxel["keys"][rows],
                weights=voxel["weights"][rows],
                latent_basis=torch.from_numpy(data["latent_basis"][i]).to(torch.float32),
                latent_coeffs=voxel["latent_coeffs"][rows],
                jacobian_basis=torch.from_numpy(data["jacobian_basis"][i]).to(torch.float32),
                jacobian_coeffs=voxel["jacobian_coeffs"][rows],
                jacobian_scales=torch.from_numpy(data["jacobian_scales"][i]).to(torch.float32),
            ).to(device)
            submaps.append(
                Submap(
                    submap_id=int(ids[i]),
                    T_W_A_encoded=check_rigid(data["submap_T_W_A_encoded"][i], "T_W_A_encoded"),
                    original=original,
                    T_W_A=check_rigid(data["submap_T_W_A"][i], "T_W_A"),
                )
            )
        for submap, fused in zip(submaps, data["submap_fused"].tolist(), strict=True):
            if fused:
                neural_map.fuse(submap)
    except (KeyError, IndexError, ValueError, TypeError, RuntimeError) as exc:
        raise MapFileError(
            f"{path}: map file content is inconsistent ({exc.__class__.__name__}: "
            f"{str(exc).splitlines()[0] if str(exc) else ''}); re-save the map"
        ) from exc
    return neural_map, submaps


def load_session(path: str | Path) -> tuple[dict, dict, dict[str, np.ndarray]]:
    """``(map header, session header, session arrays)`` of a map file with a session section.

    A file without one (saved without a session) or with an older version's (2 has none, 3 an
    older layout) is a one-line :class:`MapFileError` saying to re-run ``slam.run``.
    """
    path = Path(path)
    data = _read_npz(path)
    header = _header(path, data)
    if header.get("version") != VERSION or not isinstance(header.get("session"), dict):
        raise MapFileError(
            f"{path}: map format version {header.get('version')} holds no session data of version "
            f"{VERSION} and cannot be merged; re-run `python -m slam.run` on the sequence to write "
            f"a version {VERSION} map"
        )
    arrays = {
        name[len(SESSION_PREFIX) :]: value
        for name, value in data.items()
        if name.startswith(SESSION_PREFIX)
    }
    return header, header["session"], arrays
