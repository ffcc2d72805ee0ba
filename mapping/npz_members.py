"""The members of an ``.npz`` file: written part by part, and sized before any is read.

:func:`write_npz` writes what ``np.savez_compressed`` writes, where an array given as
:class:`Stacked` parts is written part by part, never concatenated in memory.

A map file may come from elsewhere, so nothing in it is trusted before it is checked:
:func:`list_members` reads only the zip directory and each member's ``.npy`` header (its shape
and dtype, at most a few kB each, never the data) and checks that the header's size matches the
size the zip directory declares; :func:`read_member` then reads one member, whose allocation is
the size already checked (``zipfile`` never inflates a member past its declared size, and the
``.npy`` reader allocates what the header says). What sizes a caller accepts is its business
(:mod:`mapping.map_schema` for map files).
"""

from __future__ import annotations

import math
import zipfile
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

MAX_MEMBERS = 256
"""More members than any map file holds: a zip directory beyond it is refused unread."""

MAX_NPY_HEADER_BYTES = 10_000
"""numpy's own limit on an ``.npy`` header (it refuses longer ones as untrusted)."""


class MemberError(ValueError):
    """A member whose declared sizes disagree or that is not a plain ``.npy`` array."""


@dataclass(frozen=True)
class Member:
    """One ``NAME.npy`` member: its zip entry, and the shape and dtype its header declares."""

    name: str
    info: zipfile.ZipInfo
    shape: tuple[int, ...]
    dtype: np.dtype

    @property
    def nbytes(self) -> int:
        """Bytes its array takes in memory (what reading it allocates)."""
        return math.prod(self.shape) * self.dtype.itemsize


def _npy_header(archive: zipfile.ZipFile, info: zipfile.ZipInfo) -> tuple[tuple, np.dtype, int]:
    """Shape, dtype and header length of a member, reading only its header."""
    with archive.open(info) as stream:
        version = np.lib.format.read_magic(stream)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(
                stream, max_header_size=MAX_NPY_HEADER_BYTES
            )
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(
                stream, max_header_size=MAX_NPY_HEADER_BYTES
            )
        else:
            raise MemberError(f"{info.filename}: .npy version {version} is not supported")
        header_bytes = stream.tell()
    if fortran or dtype.hasobject or any(not isinstance(n, int) or n < 0 for n in shape):
        raise MemberError(f"{info.filename}: not a plain C-ordered array")
    return tuple(shape), dtype, header_bytes


def list_members(archive: zipfile.ZipFile) -> dict[str, Member]:
    """Every ``.npy`` member by name (without ``.npy``), each header's size checked against the
    zip directory's: a member whose data would not be exactly its declared size is refused."""
    infos = archive.infolist()
    if len(infos) > MAX_MEMBERS:
        raise MemberError(f"{len(infos)} members (a map file holds fewer than {MAX_MEMBERS})")
    members = {}
    for info in infos:
        if not info.filename.endswith(".npy") or info.is_dir():
            raise MemberError(f"{info.filename}: not an .npy member")
        shape, dtype, header_bytes = _npy_header(archive, info)
        member = Member(info.filename[: -len(".npy")], info, shape, dtype)
        if header_bytes + member.nbytes != info.file_size:
            raise MemberError(
                f"{info.filename}: its header declares {member.nbytes} bytes of {shape} "
                f"{dtype} but the zip entry holds {info.file_size - header_bytes}"
            )
        if member.name in members:
            raise MemberError(f"{info.filename}: stored twice")
        members[member.name] = member
    return members


def read_member(archive: zipfile.ZipFile, member: Member) -> np.ndarray:
    """The array of a listed member (sizes checked by :func:`list_members`)."""
    with archive.open(member.info) as stream:
        array = np.lib.format.read_array(
            stream, allow_pickle=False, max_header_size=MAX_NPY_HEADER_BYTES
        )
        if stream.read(1):  # reading on to the end also checks the member's CRC
            raise MemberError(f"{member.info.filename}: data beyond its declared size")
    if array.shape != member.shape or array.dtype != member.dtype:
        raise MemberError(f"{member.info.filename}: changed while it was read")
    return array


class Stacked(NamedTuple):
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


def write_npz(f, arrays: dict[str, np.ndarray | Stacked]) -> None:
    """``np.savez_compressed(f, **arrays)`` (the same entries in the same order, each written
    as ``np.save`` would), where a :class:`Stacked` entry is written part by part."""
    with zipfile.ZipFile(f, mode="w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as zipf:
        for name, value in arrays.items():
            with zipf.open(f"{name}.npy", "w", force_zip64=True) as fid:  # zip64 as numpy does
                if isinstance(value, Stacked):
                    _write_stacked(fid, value.parts)
                else:
                    np.lib.format.write_array(fid, np.asanyarray(value), allow_pickle=False)
