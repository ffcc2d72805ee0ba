"""Saving and loading a neural map with its submaps (docs/design.md §3.7).

Format ``neural-remap-slam/map`` version 5: one compressed ``.npz`` (numpy zip, deflate) written
and read with ``allow_pickle=False``, so loading never executes code. It holds what cannot be
derived: every submap's compact original encoding (:class:`~mapping.compact_block.CompactBlock`)
and its poses. The global map is not stored: it is the fusion of the fused submaps' placed blocks,
rebuilt on load (equal to the saved one up to float32 rounding of the fusion order).

* ``header``: a 0-d unicode array holding JSON: format, version, voxel size, the map config, the
  model identity (:meth:`PriorModel.identity`), latent channels, storage dtype, submap count.
* per submap (``S`` of them, in order): ``submap_ids (S,) int64``, ``submap_fused (S,) bool``,
  ``submap_T_W_A_encoded (S,4,4)`` and ``submap_T_W_A (S,4,4)`` float64, ``submap_offsets (S+1,)
  int64`` (rows of submap ``i`` are ``offsets[i]:offsets[i+1]`` in the voxel arrays),
  ``latent_basis (S,C,kF)``, ``latent_scales (S,kF)``, ``jacobian_basis (S,C,kJ)`` and
  ``jacobian_scales (S,kJ)`` float32.
* per voxel of every submap: ``key_deltas`` int64 (a submap's first packed key, see
  :mod:`common.voxel_keys`, then the step from each of its sorted keys to the next: neighbours
  make small steps, which deflate stores in a ninth of the keys' bytes), ``weights`` float32,
  ``latent_coeffs (N,kF,3)`` in the header's ``storage_dtype`` and ``jacobian_coeffs
  (N,kJ,3,3)`` in its ``jacobian_storage`` (``int8``, ``float16`` and ``float32`` as numpy
  types, ``int4`` as int8 codes within +-7; ``bfloat16`` as its raw ``int16`` bits). A submap's
  latents are ``(latent_basis[i] * latent_scales[i]) @ latent_coeffs[rows]`` (channels x 3 per
  voxel), its Jacobians ``(jacobian_basis[i] * jacobian_scales[i]) @ jacobian_coeffs[rows]``;
  the scales are the steps of integer codes, 1 for a float format.

Version 3 adds an optional *session* section (docs/design.md §4): ``header["session"]`` (JSON)
and arrays named ``session_*``, written and read opaquely here (the SLAM layer defines them; see
``slam.algorithm.merge.session``). Version 4 changes only that section (frames'
anchor-relative poses as float32 quaternion and translation instead of float64 matrices).
Version 5 changes only the map's arrays: ``key_deltas`` instead of absolute ``keys`` and
``latent_scales`` for int8 latents. Version 2 to 4 files still load as maps (absolute keys, no
latent scales); :func:`load_session` reads the session section of versions 4 and 5 and refuses
the older ones.

Files are written to a temporary file in the target folder and moved into place. The per-voxel
arrays are written submap by submap (:class:`~mapping.npz_members.Stacked`): the file is the one
``np.savez_compressed`` writes of their concatenation, without the concatenation in memory (that
copy of every submap's encoding used to set a run's peak RSS).

A map file may come from elsewhere: :func:`read_map_file` checks every member's declared size
against what the header implies before reading any (:mod:`mapping.map_schema`), validates the
header's config with its bounds, and never lets the file choose the prior file or the device
(:data:`COMMAND_FIELDS`): the reading command's own are used and the file's model identity is
only compared.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from pydantic import ValidationError

from common.atomic_io import atomic_path
from mapping.compact_block import CompactBlock, storage_dtype
from mapping.config import MapConfig
from mapping.errors import MapFileError
from mapping.map_schema import (
    MAP_ARRAYS,
    MAP_ARRAYS_BEFORE_5,
    MAX_CHANNELS,
    MAX_HEADER_CHARS,
    MAX_SUBMAPS,
    Spec,
    check_inflation,
    check_members,
)
from mapping.networks import PriorModel
from mapping.neural_map import NeuralMap, Submap
from mapping.npz_members import (
    Member,
    MemberError,
    Stacked,
    list_members,
    read_member,
    write_npz,
)
from mapping.transform import check_rigid

FORMAT = "neural-remap-slam/map"
VERSION = 5
READABLE_VERSIONS = (2, 3, 4, 5)
SESSION_VERSIONS = (4, VERSION)
"""Versions whose session section :func:`load_session` reads (5 changed only the map's arrays)."""
SESSION_PREFIX = "session_"
_PER_VOXEL = ("key_deltas", "weights", "latent_coeffs", "jacobian_coeffs")


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
    arrays: dict[str, np.ndarray | Stacked] = {
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
        "latent_scales": (k_f,),
    }
    for name, shape in shapes.items():
        if any(tuple(getattr(o, name).shape) != shape for o in originals):
            raise ValueError(f"save: every submap's {name} must be {shape}")
        arrays[name] = np.zeros((len(originals), *shape), np.float32)
        for i, o in enumerate(originals):
            arrays[name][i] = _to_numpy(getattr(o, name))
    empty = {  # zero-row templates keep shapes and dtypes when there are no voxels at all
        "key_deltas": np.zeros(0, np.int64),
        "weights": np.zeros(0, np.float32),
        "latent_coeffs": _to_numpy(torch.zeros(0, k_f, 3, dtype=dtype)),
        "jacobian_coeffs": _to_numpy(torch.zeros(0, k_j, 3, 3, dtype=jac_dtype)),
    }
    per_voxel = {"key_deltas": [_key_deltas(o.keys) for o in originals]}
    for name in _PER_VOXEL[1:]:  # views of the submaps' tensors, written one after the other
        per_voxel[name] = [_to_numpy(getattr(o, name)) for o in originals]
    for name, parts in per_voxel.items():
        arrays[name] = Stacked([empty[name], *parts])
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
        write_npz(f, arrays)


class MapFileData(NamedTuple):
    """A map file's header, its map config (:func:`map_config`) and the arrays read from it."""

    header: dict
    cfg: MapConfig
    arrays: dict[str, np.ndarray]


COMMAND_FIELDS = ("device", "weights_path")
"""Map settings that belong to the command reading a map, never to the file: which prior file is
opened and which device is used are not a stored map's to choose."""

_FILE_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError)


def _parse_header(path: Path, archive: zipfile.ZipFile, members: dict[str, Member]) -> dict:
    if "header" not in members:
        raise MapFileError(f"{path}: no map header; this is not a {FORMAT} file")
    text = members["header"]
    if text.shape != () or text.dtype.kind != "U" or text.nbytes > 4 * MAX_HEADER_CHARS:
        raise MapFileError(f"{path}: map header is not a JSON string of at most {MAX_HEADER_CHARS}")
    try:
        header = json.loads(str(read_member(archive, text)))
    except (json.JSONDecodeError, TypeError, RecursionError) as exc:
        raise MapFileError(
            f"{path}: corrupt map header ({type(exc).__name__}); re-save the map"
        ) from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise MapFileError(f"{path}: not a {FORMAT} file")
    if header.get("version") not in READABLE_VERSIONS:
        raise MapFileError(
            f"{path}: map format version {header.get('version')} is not supported (this code "
            f"reads versions {READABLE_VERSIONS}); regenerate it by running `python -m slam.run` "
            "on the sequence again"
        )
    return header


def map_config(path: Path, header: dict, settings: MapConfig | None = None) -> MapConfig:
    """The map config of a file's header, validated (bounds included), with the
    :data:`COMMAND_FIELDS` of ``settings`` (the reading command's; default: the defaults)."""
    stored = header.get("config")
    if not isinstance(stored, dict):
        raise MapFileError(f"{path}: the map header holds no config; re-save the map")
    settings = settings or MapConfig()
    values = {k: v for k, v in stored.items() if k not in COMMAND_FIELDS}
    try:
        return MapConfig(**values, **{k: getattr(settings, k) for k in COMMAND_FIELDS})
    except ValidationError as exc:
        error = exc.errors()[0]
        where = ".".join(str(p) for p in error["loc"]) or "config"
        raise MapFileError(
            f"{path}: invalid map config in its header: mapping.{where}: {error['msg']}; "
            "this file was not written by slam.run"
        ) from None


def _dims(path: Path, header: dict, cfg: MapConfig) -> dict[str, int]:
    """Array dimensions the header fixes."""
    submaps, channels = header.get("num_submaps"), header.get("latent_channels")
    bounds = (("num_submaps", submaps, MAX_SUBMAPS), ("latent_channels", channels, MAX_CHANNELS))
    for name, value, top in bounds:
        if type(value) is not int or not 0 <= value <= top:
            raise MapFileError(f"{path}: header {name} {value!r} is not a count up to {top}")
    return {
        "S": submaps,
        "S+1": submaps + 1,
        "C": channels,
        "kF": min(cfg.latent_rank, channels),
        "kJ": min(cfg.jacobian_rank, channels),
    }


def read_map_file(
    path: str | Path,
    settings: MapConfig | None = None,
    session: dict[str, Spec] | None = None,
) -> MapFileData:
    """Header, config and arrays of a map file, every size checked before anything is read
    (:mod:`mapping.map_schema`); any problem is a one-line :class:`MapFileError`.

    ``settings``: the reading command's map settings (:func:`map_config`). ``session``: read
    the session section's arrays against these specs, and refuse a file without a current
    session section (``None``: every ``session_*`` array, sized by the file's bound alone).
    """
    path = Path(path)
    if not path.is_file():
        raise MapFileError(f"{path}: map file not found; check the path")
    try:
        with zipfile.ZipFile(path) as archive:
            members = list_members(archive)
            header = _parse_header(path, archive, members)
            cfg = map_config(path, header, settings)
            dims = _dims(path, header, cfg)
            specs = MAP_ARRAYS if header["version"] >= 5 else MAP_ARRAYS_BEFORE_5
            offsets = check_members(members, {"submap_offsets": specs["submap_offsets"]}, dims)
            first = read_member(archive, offsets["submap_offsets"])
            dims["N"] = int(first[-1]) if len(first) and first[-1] >= 0 else -1
            chosen = check_members(members, specs, dims)
            chosen.update(_session_members(path, header, members, dims, session))
            check_inflation(chosen, path.stat().st_size)
            arrays = {name: read_member(archive, member) for name, member in chosen.items()}
    except MapFileError:
        raise
    except MemberError as exc:
        raise MapFileError(
            f"{path}: map file content is inconsistent ({exc}); write it again with slam.run"
        ) from None
    except _FILE_ERRORS as exc:
        raise MapFileError(
            f"{path}: not a readable neural map file (truncated or foreign: "
            f"{exc.__class__.__name__}); write it again with slam.run"
        ) from exc
    return MapFileData(header, cfg, arrays)


def _session_members(
    path: Path,
    header: dict,
    members: dict[str, Member],
    dims: dict[str, int],
    specs: dict[str, Spec] | None,
) -> dict[str, Member]:
    if specs is None:
        return {name: m for name, m in members.items() if name.startswith(SESSION_PREFIX)}
    _require_session(path, header)
    prefixed = {SESSION_PREFIX + name: spec for name, spec in specs.items()}
    return check_members(members, prefixed, dims)


def _require_session(path: Path, header: dict) -> None:
    if header.get("version") not in SESSION_VERSIONS or not isinstance(header.get("session"), dict):
        raise MapFileError(
            f"{path}: map format version {header.get('version')} holds no session data of version "
            f"{VERSION} and cannot be merged; re-run `python -m slam.run` on the sequence to write "
            f"a version {VERSION} map"
        )


def load_map(
    path: str | Path,
    model: PriorModel | None = None,
    settings: MapConfig | None = None,
    *,
    check_model: bool = True,
    data: MapFileData | None = None,
) -> tuple[NeuralMap, list[Submap]]:
    """Read a map written by :func:`save_map`; any problem is a one-line :class:`MapFileError`.

    ``model``: the prior to decode with (default: the one ``settings`` names; the file's own
    ``weights_path`` and ``device`` are never used, :data:`COMMAND_FIELDS`). The model must be
    the one the map was encoded with, unless ``check_model`` is off (for reading voxel
    positions only). ``data``: the file already read by :func:`read_map_file`. The global map is
    rebuilt by fusing the fused submaps in the order they are stored.
    """
    path = Path(path)
    header, cfg, arrays = data or read_map_file(path, settings)
    try:
        neural_map = NeuralMap(cfg, model)
    except (OSError, ValueError) as exc:  # the command's own prior or device
        raise MapFileError(f"{path}: cannot load it: {' '.join(str(exc).split())}") from None
    identity = neural_map.model.identity()
    if check_model and header.get("model_identity") != identity:
        raise MapFileError(
            f"{path}: map was encoded with model {str(header.get('model_identity'))[:32]} but "
            f"the loaded model is {identity}; load it with the same prior weights "
            "(mapping.weights_path)"
        )
    if header.get("latent_channels") != neural_map.model.latent_channels:
        raise MapFileError(f"{path}: latent size does not match the model")
    try:
        submaps = _submaps(header, arrays, neural_map.device)
        for submap, fused in zip(submaps, arrays["submap_fused"].tolist(), strict=True):
            if fused:
                neural_map.fuse(submap)
    except (KeyError, IndexError, ValueError, TypeError, RuntimeError) as exc:
        raise MapFileError(
            f"{path}: map file content is inconsistent ({exc.__class__.__name__}: "
            f"{str(exc).splitlines()[0] if str(exc) else ''}); re-save the map"
        ) from exc
    return neural_map, submaps


def _key_deltas(keys: torch.Tensor) -> np.ndarray:
    """A submap's sorted keys as its first key and the steps to each next one: neighbouring
    voxels make small steps, which deflate stores in a fraction of the keys' bytes."""
    keys = _to_numpy(keys)
    return np.diff(keys, prepend=np.zeros(1, np.int64)) if len(keys) else keys


def _keys_of_deltas(deltas: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """The keys :func:`_key_deltas` coded, submap by submap (rows ``offsets[i]:offsets[i+1]``);
    int64 wraps around both ways, so any file decodes to the keys it was written from."""
    sums = np.cumsum(deltas.astype(np.int64, copy=False))
    starts = np.repeat(offsets[:-1], np.diff(offsets))
    before = np.concatenate([np.zeros(1, np.int64), sums])[starts]
    return sums - before


def _submaps(header: dict, data: dict[str, np.ndarray], device: torch.device) -> list[Submap]:
    dtype = storage_dtype(header["storage_dtype"])
    jac_dtype = storage_dtype(header["jacobian_storage"])
    offsets = data["submap_offsets"]
    n_sub = int(header["num_submaps"])
    ids = data["submap_ids"]
    if offsets.shape != (n_sub + 1,) or offsets[0] != 0 or np.any(np.diff(offsets) < 0):
        raise ValueError("submap offsets are not a monotone (S+1,) array starting at 0")
    if offsets[-1] != data["weights"].shape[0] or len(set(ids.tolist())) != n_sub:
        raise ValueError("submap offsets, ids and voxel arrays disagree")
    if "key_deltas" in data:
        keys = _keys_of_deltas(data["key_deltas"], offsets)
        latent_scales = data["latent_scales"]
    else:  # before version 5: absolute keys, float latents
        keys = data["keys"].astype(np.int64, copy=False)
        latent_scales = np.ones(data["latent_basis"].shape[::2], np.float32)
    voxel = {
        "keys": torch.from_numpy(keys),
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
            latent_scales=torch.from_numpy(latent_scales[i]).to(torch.float32),
        ).to(device)
        submaps.append(
            Submap(
                submap_id=int(ids[i]),
                T_W_A_encoded=check_rigid(data["submap_T_W_A_encoded"][i], "T_W_A_encoded"),
                original=original,
                T_W_A=check_rigid(data["submap_T_W_A"][i], "T_W_A"),
            )
        )
    return submaps


def load_session(
    path: str | Path, specs: dict[str, Spec] | None = None, data: MapFileData | None = None
) -> tuple[dict, dict, dict[str, np.ndarray]]:
    """``(map header, session header, session arrays)`` of a map file with a session section
    (``specs``: what its arrays may be, :func:`read_map_file`; ``data``: the file already read
    with them).

    A file without one (saved without a session) or with an older version's (2 has none, 3 an
    older layout) is a one-line :class:`MapFileError` saying to re-run ``slam.run``.
    """
    path = Path(path)
    header, _, arrays = data or read_map_file(path, session=specs)
    _require_session(path, header)
    session = {
        name[len(SESSION_PREFIX) :]: value
        for name, value in arrays.items()
        if name.startswith(SESSION_PREFIX)
    }
    return header, header["session"], session
