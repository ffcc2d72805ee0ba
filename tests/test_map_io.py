"""Saving and loading neural maps: exact round trip of what is stored, clear errors otherwise."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from mapping.compact_block import FIELDS
from mapping.config import MapConfig
from mapping.errors import MapFileError
from mapping.map_io import COMMAND_FIELDS, load_map, save_map
from mapping.neural_map import NeuralMap
from tests.helpers import seeded_prior, sphere_points, written_before_version_5

torch.set_num_threads(1)


def test_save_load_round_trip(saved_map) -> None:
    nm, subs, path = saved_map
    loaded, loaded_subs = load_map(path, seeded_prior())
    # the global map is rebuilt from the submaps: equal up to float32 rounding of fusion order
    a, b = nm.voxel_block(), loaded.voxel_block()
    assert torch.equal(a.keys, b.keys)
    assert (a.latents - b.latents).abs().max() < 1e-6
    assert torch.allclose(nm._store.weights64(), loaded._store.weights64(), rtol=1e-12, atol=1e-9)
    # the stored settings come back; device and prior file are the loader's own
    own = set(COMMAND_FIELDS)
    assert loaded.cfg.model_dump(exclude=own) == nm.cfg.model_dump(exclude=own)
    assert [s.submap_id for s in loaded_subs] == [10, 11, 12]
    for s, t in zip(subs, loaded_subs, strict=True):
        assert s.fused == t.fused
        assert np.array_equal(s.T_W_A, t.T_W_A) and np.array_equal(s.T_W_A_encoded, t.T_W_A_encoded)
        for name in FIELDS:  # what is stored comes back bit for bit
            assert torch.equal(getattr(s.original, name), getattr(t.original, name))
        assert torch.equal(nm.placed(s).latents, loaded.placed(t).latents)
    # the loaded map keeps working: removing what was fused empties it
    loaded.remove(loaded_subs[0])
    loaded.remove(loaded_subs[1])
    assert loaded.num_voxels == 0
    with pytest.raises(ValueError, match="not fused"):
        loaded.remove(loaded_subs[2])
    assert not list(path.parent.glob("*.tmp"))


def test_truncated_file_is_rejected(saved_map) -> None:
    _, _, path = saved_map
    data = path.read_bytes()
    bad = path.with_name("truncated.npz")
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapFileError, match=r"truncated\.npz") as info:
        load_map(bad, seeded_prior())
    assert "\n" not in str(info.value)


def test_foreign_files_are_rejected(tmp_path: Path) -> None:
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"definitely not a zip file")
    with pytest.raises(MapFileError, match=r"junk\.npz"):
        load_map(junk, seeded_prior())
    other = tmp_path / "other.npz"
    np.savez(other, x=np.arange(3))
    with pytest.raises(MapFileError, match="no map header"):
        load_map(other, seeded_prior())
    with pytest.raises(MapFileError, match="not found"):
        load_map(tmp_path / "missing.npz", seeded_prior())


def _rewrite_header(path: Path, out: Path, **changes) -> None:
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    header = json.loads(str(arrays["header"]))
    header.update(changes)
    arrays["header"] = np.array(json.dumps(header))
    np.savez(out, **arrays)


def test_wrong_version_and_format_are_rejected(saved_map, tmp_path: Path) -> None:
    _, _, path = saved_map
    _rewrite_header(path, tmp_path / "v99.npz", version=99)
    with pytest.raises(MapFileError, match="version 99"):
        load_map(tmp_path / "v99.npz", seeded_prior())
    _rewrite_header(path, tmp_path / "fmt.npz", format="something-else")
    with pytest.raises(MapFileError, match="not a neural-remap-slam/map file"):
        load_map(tmp_path / "fmt.npz", seeded_prior())


def test_model_mismatch_is_rejected(saved_map) -> None:
    _, _, path = saved_map
    with pytest.raises(MapFileError, match="same prior weights"):
        load_map(path, seeded_prior(seed=1))


def test_missing_arrays_are_rejected(saved_map, tmp_path: Path) -> None:
    _, _, path = saved_map
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(tmp_path / "cut.npz", "w") as dst:
        for item in src.infolist():
            if not item.filename.startswith("latent_coeffs"):
                dst.writestr(item, src.read(item.filename))
    with pytest.raises(MapFileError, match="inconsistent"):
        load_map(tmp_path / "cut.npz", seeded_prior())


def _rewrite_arrays(path: Path, out: Path, **changes) -> None:
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays.update(changes)
    np.savez_compressed(out, **arrays)


def test_version_4_files_load_as_written(saved_map, tmp_path: Path) -> None:
    """Before version 5 a file held absolute keys and no latent scales (float latents)."""
    _, subs, path = saved_map
    written_before_version_5(path, tmp_path / "v4.npz", 4, subs)
    loaded, loaded_subs = load_map(tmp_path / "v4.npz", seeded_prior())
    for s, t in zip(subs, loaded_subs, strict=True):
        for name in FIELDS:
            assert torch.equal(getattr(s.original, name), getattr(t.original, name))
    assert torch.equal(
        loaded.voxel_block().latents, load_map(path, seeded_prior())[0].voxel_block().latents
    )


def test_keys_are_stored_as_steps_within_each_submap(saved_map) -> None:
    _, subs, path = saved_map
    with np.load(path, allow_pickle=False) as npz:
        deltas, offsets = npz["key_deltas"], npz["submap_offsets"]
    for s, start in zip(subs, offsets, strict=False):
        keys = s.original.keys.numpy()
        assert deltas[start] == keys[0]  # each submap starts from its own first key
        assert np.array_equal(np.cumsum(deltas[start : start + len(keys)]), keys)


def test_version_1_files_get_a_regenerate_hint(saved_map, tmp_path: Path) -> None:
    _, _, path = saved_map
    _rewrite_header(path, tmp_path / "v1.npz", version=1)
    with pytest.raises(MapFileError, match=r"v1\.npz: map format version 1 .*python -m slam\.run"):
        load_map(tmp_path / "v1.npz", seeded_prior())


@pytest.mark.parametrize("bad", [0.0, -3.0, float("nan")])
def test_bad_weights_are_rejected_on_load(saved_map, tmp_path: Path, bad: float) -> None:
    _, _, path = saved_map
    with np.load(path) as npz:
        weights = npz["weights"].copy()
    weights[5] = bad
    _rewrite_arrays(path, tmp_path / "w.npz", weights=weights)
    with pytest.raises(MapFileError, match=r"w\.npz: .*weights must be finite and positive"):
        load_map(tmp_path / "w.npz", seeded_prior())


def test_nan_coefficients_are_rejected_on_load(saved_map, tmp_path: Path) -> None:
    _, _, path = saved_map
    with np.load(path) as npz:
        coeffs = npz["latent_coeffs"].copy()
    coeffs[3, 0, 1] = np.nan
    _rewrite_arrays(path, tmp_path / "nan.npz", latent_coeffs=coeffs)
    with pytest.raises(MapFileError, match="NaN"):
        load_map(tmp_path / "nan.npz", seeded_prior())


def test_empty_map_round_trips(tmp_path: Path) -> None:
    cfg = MapConfig(device="cpu")
    nm = NeuralMap(cfg, seeded_prior())
    save_map(nm, tmp_path / "empty.npz", [])
    loaded, subs = load_map(tmp_path / "empty.npz", seeded_prior())
    assert loaded.num_voxels == 0 and subs == []
    # a submap that was encoded but never fused (and one that encoded nothing)
    p, n = sphere_points(800, (0.1, 0.2, 0.3), 4)
    lone = nm.encode(7, p, n, np.eye(4))
    nothing = nm.encode(8, np.zeros((0, 3)), np.zeros((0, 3)), np.eye(4))
    save_map(nm, tmp_path / "unfused.npz", [lone, nothing])
    loaded, subs = load_map(tmp_path / "unfused.npz", seeded_prior())
    assert loaded.num_voxels == 0
    assert [s.fused for s in subs] == [False, False]
    assert torch.equal(subs[0].original.keys, lone.original.keys)
    assert subs[1].original.num_voxels == 0
    loaded.fuse(subs[0])
    nm.fuse(lone)
    assert torch.equal(loaded.voxel_block().latents, nm.voxel_block().latents)


@pytest.mark.parametrize(
    ("dtype", "jacobians"),
    [("float16", "int8"), ("bfloat16", "int8"), ("float32", "int8"), ("int8", "int4")],
)
def test_every_storage_dtype_round_trips(tmp_path: Path, dtype: str, jacobians: str) -> None:
    cfg = MapConfig(
        device="cpu", min_points_per_voxel=1, storage_dtype=dtype, jacobian_storage=jacobians
    )
    nm = NeuralMap(cfg, seeded_prior())
    p, n = sphere_points(1500, (0.0, 0.0, 0.0), 5)
    sub = nm.encode(0, p, n, np.eye(4))
    nm.fuse(sub)
    save_map(nm, tmp_path / f"{dtype}.npz", [sub])
    loaded, subs = load_map(tmp_path / f"{dtype}.npz", seeded_prior())
    assert subs[0].original.latent_coeffs.dtype == getattr(torch, dtype)
    for name in FIELDS:
        assert torch.equal(getattr(subs[0].original, name), getattr(sub.original, name))
    assert torch.equal(loaded.voxel_block().latents, nm.voxel_block().latents)


def test_stacked_arrays_are_written_as_savez_compressed_writes_their_concatenation() -> None:
    """The per-voxel arrays are written part by part: the file is byte for byte the one
    ``np.savez_compressed`` writes of the concatenated arrays (dtype promotion included)."""
    import io

    from mapping.npz_members import Stacked, write_npz

    rng = np.random.default_rng(0)
    parts = {
        "keys": [np.zeros(0, np.int64), rng.integers(0, 1 << 40, 7), rng.integers(0, 9, 0)],
        "latent": [rng.normal(size=(n, 4, 3)).astype(np.float32) for n in (0, 5, 0, 300_000)],
        "bits": [np.zeros((0, 2, 3, 3), np.int16), rng.integers(-9, 9, (3, 2, 3, 3), np.int16)],
        "mixed": [np.zeros(0, np.float32), np.ones(4, np.float64)],  # promoted to float64
    }
    plain = {"ids": np.arange(4), "header": np.array(json.dumps({"a": 1}))}
    ours, reference = io.BytesIO(), io.BytesIO()
    write_npz(ours, {**plain, **{name: Stacked(p) for name, p in parts.items()}})
    np.savez_compressed(reference, **plain, **{n: np.concatenate(p) for n, p in parts.items()})
    assert ours.getvalue() == reference.getvalue()
    with pytest.raises(ValueError, match="do not stack"):
        write_npz(io.BytesIO(), {"x": Stacked([np.zeros((1, 2)), np.zeros((1, 3))])})
