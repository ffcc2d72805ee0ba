"""What a merge takes, and the sessions it refuses before any work: maps that cannot share one
grid (voxel size, prior, latent storage, sensor), sessions without place descriptors, and a
session given twice (the same run, a copy, or a merged run with one of the runs it joined)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

from mapping.neural_map import NeuralMap, Submap
from slam.algorithm.merge.session import SessionRecord


class MergeError(ValueError):
    """Sessions that cannot be merged; the message is one line saying which and why."""


@dataclass
class SessionInput:
    """One run to merge: its name (run folder), session record and submaps (original encodings)."""

    name: str
    session: SessionRecord
    submaps: list[Submap]


LATENT_STORAGE_FIELDS = ("storage_dtype", "jacobian_storage", "latent_rank", "jacobian_rank")
"""Mapping settings that fix how latents are stored: maps differing in one cannot share a grid."""


def check_compatible(inputs: list[SessionInput], maps: list[NeuralMap]) -> None:
    """Refuse maps that cannot share one grid: voxel size, prior, storage or sensor differ."""
    first, reference = inputs[0], maps[0]
    for item, other in zip(inputs[1:], maps[1:], strict=True):
        if other.voxel_size_m != reference.voxel_size_m:
            raise MergeError(
                f"{item.name}: voxel size {other.voxel_size_m} m differs from {first.name}'s "
                f"{reference.voxel_size_m} m; re-run it with mapping.voxel_size_m="
                f"{reference.voxel_size_m}"
            )
        if other.model.identity() != reference.model.identity():
            raise MergeError(
                f"{item.name}: encoded with another prior than {first.name}; re-run it with the "
                "same mapping.weights_path"
            )
        cfg_a, cfg_b = reference.cfg, other.cfg
        if any(getattr(cfg_a, k) != getattr(cfg_b, k) for k in LATENT_STORAGE_FIELDS):
            raise MergeError(
                f"{item.name}: latent storage differs from {first.name}'s; re-run it with the "
                "same mapping settings"
            )
        if item.session.sensor != first.session.sensor:
            raise MergeError(
                f"{item.name}: sensor {item.session.sensor} differs from {first.name}'s "
                f"{first.session.sensor}; only runs of one sensor can be merged"
            )
    check_distinct(inputs)
    for item in inputs:
        if not item.session.descriptors:
            raise MergeError(
                f"{item.name}: no place descriptors stored (loop closure was off); re-run it "
                "with loop_closure.enabled=true"
            )


def check_distinct(inputs: list[SessionInput]) -> None:
    """Refuse a session given twice (the same run, a copy of it, or a merged run and one of the
    runs it joined): the merge would hold every one of its submaps and frames twice."""
    seen: dict[str, str] = {}
    for item in inputs:
        identities = item.session.identities()
        for identity in identities:
            if identity in seen:
                raise MergeError(
                    f"{item.name}: holds the same session as {seen[identity]} (session "
                    f"{identity[:12]}): the merge would hold its submaps and frames twice; "
                    "give every run once"
                )
        seen.update(dict.fromkeys(identities, item.name))


def merged_session_id(inputs: list[SessionInput]) -> str:
    """The id of a merge of ``inputs``: a hash of theirs (merging the same runs again gives the
    same session, which a later merge then refuses to take twice)."""
    joined = ",".join(item.session.session_id for item in inputs)
    return hashlib.sha256(f"merge:{joined}".encode()).hexdigest()[:32]
