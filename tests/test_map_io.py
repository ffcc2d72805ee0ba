"""Saving and loading neural maps: bit-exact round trip and clear errors for bad files."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from mapping.config import MapConfig
from mapping.errors import MapFileError
from mapping.networks import PriorModel
from mapping.neural_map import NeuralMap

torch.set_num_threads(1)


def _model(seed: int = 0) -> PriorModel:
    torch.manual_seed(seed)
    return PriorModel().eval()


def _sphere(n: int, centre, seed: int):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * 0.3 + np.asarray(centre), d


@pytest.fixture()
def saved(tmp_path: Path):
    cfg = MapConfig(min_points_per_voxel=1, min_weight_to_decode=1.0, device="cpu")
    nm = NeuralMap(cfg, _model())
    subs = []
    for i, centre in enumerate([(0, 0, 0), (0.25, 0.1, 0), (0.5, 0.0, 0.1)]):
        p, n = _sphere(1500, centre, i)
        subs.append(nm.encode(10 + i, p, n, np.eye(4)))
    nm.fuse(subs[0])
    nm.fuse(subs[1])
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ np.eye(3)
    T[:3, 3] = [0.0123, -0.0456, 0.078]
    nm.move(subs[1], T)
    nm.move(subs[2], T)  # never fused
    path = tmp_path / "map.npz"
    nm.save(path, subs)
    return nm, subs, path


def test_save_load_is_bit_exact(saved) -> None:
    nm, subs, path = saved
    loaded, loaded_subs = NeuralMap.load(path, _model())
    a, b = nm.voxel_block(), loaded.voxel_block()
    for name in ("keys", "latents", "weights", "jacobians"):
        assert torch.equal(getattr(a, name), getattr(b, name))
    assert torch.equal(nm._weights64(), loaded._weights64())
    assert loaded.cfg == nm.cfg
    assert [s.submap_id for s in loaded_subs] == [10, 11, 12]
    for s, t in zip(subs, loaded_subs, strict=True):
        assert s.fused == t.fused
        assert np.array_equal(s.T_W_A, t.T_W_A) and np.array_equal(s.T_W_A_encoded, t.T_W_A_encoded)
        for name in ("keys", "latents", "weights", "jacobians"):
            assert torch.equal(getattr(s.original, name), getattr(t.original, name))
            assert torch.equal(getattr(s.placed, name), getattr(t.placed, name))
        assert (t.placed is t.original) == (s.placed is s.original)
    # the loaded map keeps working: removing what was fused empties it
    loaded.remove(loaded_subs[0])
    loaded.remove(loaded_subs[1])
    assert loaded.num_voxels == 0
    with pytest.raises(ValueError, match="not fused"):
        loaded.remove(loaded_subs[2])
    assert not list(path.parent.glob("*.tmp"))


def test_truncated_file_is_rejected(saved) -> None:
    _, _, path = saved
    data = path.read_bytes()
    bad = path.with_name("truncated.npz")
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapFileError, match=r"truncated\.npz") as info:
        NeuralMap.load(bad, _model())
    assert "\n" not in str(info.value)


def test_foreign_files_are_rejected(tmp_path: Path) -> None:
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"definitely not a zip file")
    with pytest.raises(MapFileError, match=r"junk\.npz"):
        NeuralMap.load(junk, _model())
    other = tmp_path / "other.npz"
    np.savez(other, x=np.arange(3))
    with pytest.raises(MapFileError, match="no map header"):
        NeuralMap.load(other, _model())
    with pytest.raises(MapFileError, match="not found"):
        NeuralMap.load(tmp_path / "missing.npz", _model())


def _rewrite_header(path: Path, out: Path, **changes) -> None:
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    header = json.loads(str(arrays["header"]))
    header.update(changes)
    arrays["header"] = np.array(json.dumps(header))
    np.savez(out, **arrays)


def test_wrong_version_and_format_are_rejected(saved, tmp_path: Path) -> None:
    _, _, path = saved
    _rewrite_header(path, tmp_path / "v99.npz", version=99)
    with pytest.raises(MapFileError, match="version 99"):
        NeuralMap.load(tmp_path / "v99.npz", _model())
    _rewrite_header(path, tmp_path / "fmt.npz", format="something-else")
    with pytest.raises(MapFileError, match="not a neural-remap-slam/map file"):
        NeuralMap.load(tmp_path / "fmt.npz", _model())


def test_model_mismatch_is_rejected(saved) -> None:
    _, _, path = saved
    with pytest.raises(MapFileError, match="same prior weights"):
        NeuralMap.load(path, _model(seed=1))


def test_missing_arrays_are_rejected(saved, tmp_path: Path) -> None:
    _, _, path = saved
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(tmp_path / "cut.npz", "w") as dst:
        for item in src.infolist():
            if not item.filename.startswith("s1_original_latents"):
                dst.writestr(item, src.read(item.filename))
    with pytest.raises(MapFileError, match="inconsistent"):
        NeuralMap.load(tmp_path / "cut.npz", _model())
