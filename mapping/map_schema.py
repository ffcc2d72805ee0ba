"""What a map file's members may be, checked before any member's data is read.

Each array a reader loads is described by a :class:`Spec`: the group its first dimension
belongs to (arrays of one group have one length: ``S`` submaps, ``N`` voxels, ...), its
trailing shape (numbers, or dimensions the map header fixes: ``C`` latent channels, ``kF`` and
``kJ`` basis ranks) and the dtype kinds it may have. :func:`check_members` checks every
member's declared shape (:mod:`mapping.npz_members`) against these and the sizes the header
implies, and bounds the total memory the arrays would take by the size of the file: a zip
member inflates at most about a thousandfold, and a map's latents hardly compress at all, so a
file whose arrays would take far more memory than its bytes suggest is a crafted one and is
refused unread.
"""

from __future__ import annotations

from dataclasses import dataclass

from mapping.npz_members import Member, MemberError

MAX_SUBMAPS = 1_000_000
"""More submaps than any run or merge makes (a full KITTI 00 run makes about a thousand)."""

MAX_CHANNELS = 4096
"""Latent channels a header may declare (the shipped prior has 16)."""

MAX_HEADER_CHARS = 1 << 20
"""Characters of a map file's JSON header; a merged run's header grows by about 200 a run."""

MAX_INFLATION = 64
"""Memory the arrays of a map file may take per byte of the file. A run's map takes about 1.3x its
file size (latents and Jacobians are already compact and compress little); a zip bomb takes
hundreds of times its size."""

INFLATION_ALLOWANCE_BYTES = 64 << 20
"""Memory allowed on top of :data:`MAX_INFLATION` per byte (small files compress better)."""


@dataclass(frozen=True)
class Spec:
    """What one member may be: ``group`` of its first dimension (None: a fixed shape),
    ``trailing`` shape (ints or dimension names), dtype ``kinds`` (numpy kind letters)."""

    group: str | None
    trailing: tuple[int | str, ...] = ()
    kinds: str = "f"
    required: bool = True


_SUBMAP_AND_CODES: dict[str, Spec] = {
    "submap_ids": Spec("S", (), "iu"),
    "submap_fused": Spec("S", (), "b"),
    "submap_T_W_A_encoded": Spec("S", (4, 4)),
    "submap_T_W_A": Spec("S", (4, 4)),
    "submap_offsets": Spec("S+1", (), "iu"),
    "latent_basis": Spec("S", ("C", "kF")),
    "jacobian_basis": Spec("S", ("C", "kJ")),
    "jacobian_scales": Spec("S", ("kJ",)),
    "weights": Spec("N", ()),
    "latent_coeffs": Spec("N", ("kF", 3), "fiu"),  # int8 with scales, bfloat16 as its int16 bits
    "jacobian_coeffs": Spec("N", ("kJ", 3, 3), "fiu"),  # int8 with scales
}

MAP_ARRAYS: dict[str, Spec] = {
    **_SUBMAP_AND_CODES,
    "latent_scales": Spec("S", ("kF",)),
    "key_deltas": Spec("N", (), "i"),
}
"""The arrays of the map itself (:mod:`mapping.map_io`), in the current version."""

MAP_ARRAYS_BEFORE_5: dict[str, Spec] = {**_SUBMAP_AND_CODES, "keys": Spec("N", (), "iu")}
"""The arrays of a version 2 to 4 map: absolute keys, no latent scales."""


def _shape(member: Member, spec: Spec, dims: dict[str, int]) -> tuple[int, ...]:
    trailing = tuple(dims[d] if isinstance(d, str) else d for d in spec.trailing)
    return trailing if spec.group is None else (member.shape[0] if member.shape else -1, *trailing)


def check_members(
    members: dict[str, Member], specs: dict[str, Spec], dims: dict[str, int]
) -> dict[str, Member]:
    """The members ``specs`` names, each checked against its spec; ``dims`` holds the sizes
    known so far (header dimensions, groups) and receives those of the groups seen."""
    chosen = {}
    for name, spec in specs.items():
        member = members.get(name)
        if member is None:
            if spec.required:
                raise MemberError(f"array '{name}' is missing")
            continue
        if member.dtype.kind not in spec.kinds or member.dtype.itemsize > 8:
            raise MemberError(f"array '{name}' has dtype {member.dtype}")
        expected = _shape(member, spec, dims)
        if member.shape != expected:
            raise MemberError(f"array '{name}' has shape {member.shape}, expected {expected}")
        if spec.group is not None:
            length = dims.setdefault(spec.group, member.shape[0])
            if member.shape[0] != length:
                raise MemberError(
                    f"array '{name}' has {member.shape[0]} rows but the other '{spec.group}' "
                    f"arrays {length}"
                )
        chosen[name] = member
    return chosen


def check_inflation(members: dict[str, Member], file_bytes: int) -> None:
    """Refuse arrays that would take far more memory than a map file of ``file_bytes`` holds
    (see :data:`MAX_INFLATION`)."""
    total = sum(m.nbytes for m in members.values())
    if total > MAX_INFLATION * file_bytes + INFLATION_ALLOWANCE_BYTES:
        raise MemberError(
            f"its arrays would take {total / 1e6:.0f} MB from a {file_bytes / 1e6:.1f} MB file "
            "(a crafted or damaged file)"
        )
