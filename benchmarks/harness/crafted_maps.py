"""Crafted map files, each written from one real ``map.npz``: size bombs, header lies and
broken sessions, as an attacker would make them (``tests/test_untrusted_maps.py`` and
``benchmarks/bench_reliability.py``). Standard library and numpy only."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np


def _arrays(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    return json.loads(str(arrays["header"])), arrays


def rewritten(edit):
    """A crafting of ``src`` through ``edit(header, arrays)``."""

    def craft(src: Path, dst: Path) -> None:
        header, arrays = _arrays(src)
        edit(header, arrays)
        arrays["header"] = np.array(json.dumps(header))
        np.savez_compressed(dst, **arrays)

    return craft


def _with_member(src: Path, dst: Path, name: str, write) -> None:
    """``src`` with its member ``name`` written by ``write(stream)`` instead."""
    with (
        zipfile.ZipFile(src) as source,
        zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as target,
    ):
        for info in source.infolist():
            if info.filename != f"{name}.npy":
                target.writestr(info, source.read(info))
        with target.open(f"{name}.npy", "w", force_zip64=True) as stream:
            write(stream)


def _npy_header(shape: tuple, dtype) -> bytes:
    stream = io.BytesIO()
    header = np.lib.format.header_data_from_array_1_0(np.empty((0,), dtype))
    header["shape"] = shape
    np.lib.format.write_array_header_1_0(stream, header)
    return stream.getvalue()


def _zeros(stream, count: int) -> None:
    chunk = bytes(1 << 24)
    while count > 0:
        stream.write(chunk[: min(count, len(chunk))])
        count -= len(chunk)


def inflated_member(src: Path, dst: Path) -> None:
    """``weights`` declares the map's voxel count but its entry inflates to 256 MB of zeros."""
    _, arrays = _arrays(src)
    shape = arrays["weights"].shape

    def write(stream):
        stream.write(_npy_header(shape, np.float32))
        _zeros(stream, 256 << 20)

    _with_member(src, dst, "weights", write)


def claims_10e12_elements(src: Path, dst: Path) -> None:
    """``key_deltas`` whose ``.npy`` header claims 10^12 elements (and holds none)."""
    _with_member(
        src, dst, "key_deltas", lambda stream: stream.write(_npy_header((10**12,), np.int64))
    )


def consistent_but_huge(src: Path, dst: Path) -> None:
    """Every per-voxel array and the offsets agree on 4 million voxels of zeros (288 MB from a
    file of a few hundred kB)."""
    voxels = 4_000_000
    _, arrays = _arrays(src)
    offsets = arrays["submap_offsets"].copy()
    offsets[-1] = voxels
    sizes = {
        "key_deltas": ((voxels,), np.int64),
        "weights": ((voxels,), np.float32),
        "latent_coeffs": ((voxels, 4, 3), np.float16),
        "jacobian_coeffs": ((voxels, 4, 3, 3), np.int8),
    }
    with zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as target:
        for name, value in arrays.items():
            with target.open(f"{name}.npy", "w", force_zip64=True) as stream:
                if name in sizes:
                    shape, dtype = sizes[name]
                    stream.write(_npy_header(shape, dtype))
                    _zeros(stream, int(np.prod(shape)) * np.dtype(dtype).itemsize)
                else:
                    value = offsets if name == "submap_offsets" else value
                    np.lib.format.write_array(stream, value, allow_pickle=False)


def header_edit(**config):
    """A crafting that sets ``config`` in the header's map config."""

    def edit(header, arrays):
        header["config"].update(config)

    return rewritten(edit)


def deep_json(src: Path, dst: Path) -> None:
    """A header nesting 100,000 JSON lists."""
    header, arrays = _arrays(src)
    text = json.dumps(header)
    arrays["header"] = np.array(text[:-1] + ', "x": ' + "[" * 100_000 + "]" * 100_000 + "}")
    np.savez_compressed(dst, **arrays)


def array_edit(name: str, change):
    """A crafting that replaces the array ``name`` by ``change(copy of it)``."""

    def edit(header, arrays):
        arrays[name] = change(arrays[name].copy())

    return rewritten(edit)


def session_edit(name: str, change):
    """A crafting that replaces the session array ``name`` by ``change(copy of it)``."""
    return array_edit(f"session_{name}", change)


def _nan_anchor(a):
    a[-1, 0, 3] = np.nan
    return a


def _edge_to_unknown(header, arrays):
    """One more odometry factor, from the first anchor to an anchor that does not exist."""
    ij, T, cov = (arrays[f"session_odometry_{k}"] for k in ("ij", "T", "cov"))
    first = int(arrays["session_node_ids"][0])
    arrays["session_odometry_ij"] = np.vstack([ij, np.array([[first, 12345]], ij.dtype)])
    arrays["session_odometry_T"] = np.concatenate([T, np.eye(4, dtype=T.dtype)[None]])
    arrays["session_odometry_cov"] = np.concatenate([cov, 1e-4 * np.eye(6, dtype=cov.dtype)[None]])


def _nan_positions(a):
    a = a.astype(np.float16)
    a[4, 2] = np.nan
    return a


def _parts(header, arrays):
    header["session"]["parts"] = [{"name": "x", "first_row": "zero", "rows": 5}]


def _set(index, value):
    def change(a):
        a[index] = value
        return a

    return change


CRAFTED = {
    "size: member inflating past its declared size": inflated_member,
    "size: npy header claiming 10^12 elements": claims_10e12_elements,
    "size: consistent arrays far larger than the file": consistent_but_huge,
    "header: mesh_subdivisions 200": header_edit(mesh_subdivisions=200),
    "header: voxel size inf": header_edit(voxel_size_m=float("inf")),
    "header: voxel size 1e-9": header_edit(voxel_size_m=1e-9),
    "header: encoder_table_nodes 10^6": header_edit(encoder_table_nodes=10**6),
    "header: deep JSON nesting": deep_json,
    "arrays: latent scales of rank 2": array_edit("latent_scales", lambda a: a[:, :2].copy()),
    "arrays: a zero latent scale": array_edit("latent_scales", _set((0, 0), 0.0)),
    "arrays: key steps going back": array_edit("key_deltas", _set(1, -5)),
    "session: NaN anchors": session_edit("T_W_A", _nan_anchor),
    "session: edge to an unknown anchor": rewritten(_edge_to_unknown),
    "session: descriptors 16 bytes wide": session_edit(
        "descriptor_bits", lambda a: a[:, :16].copy()
    ),
    "session: short timestamps": session_edit("timestamps", lambda a: a[:-3]),
    "session: NaN descriptor positions": session_edit("descriptor_positions", _nan_positions),
    "session: malformed parts": rewritten(_parts),
}
"""Every crafted map: ``CRAFTED[name](src_map, dst_map)`` writes it from a real map file."""
