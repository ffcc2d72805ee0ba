"""The invariants of a stored session section, checked before a merge or ``--map`` uses it.

A map file may come from elsewhere; everything a merge reads of its session is checked here
first, so that a damaged or crafted file is one ``ValueError`` naming what is wrong instead of
a traceback deep in the pose graph: anchor ids unique, every id an edge, frame, descriptor or up
direction names is an anchor, every number finite, poses rigid, covariances positive definite,
frames, timestamps and parts of one length, descriptor offsets within their keypoints.
"""

from __future__ import annotations

from typing import Any

import numpy as np

ROTATION_TOLERANCE = 1e-3
"""How far a stored rotation may be from orthonormal (the graph stores float64 rotations)."""


def _require(ok: bool, what: str) -> None:
    if not ok:
        raise ValueError(what)


def _array(arrays: dict[str, np.ndarray], name: str, shape: tuple, optional=False):
    """``arrays[name]`` with its trailing ``shape`` (``-1``: any length) checked."""
    if name not in arrays:
        _require(optional, f"session array '{name}' is missing")
        return np.zeros((0, *shape[1:]))
    value = np.asarray(arrays[name])
    fits = value.ndim == len(shape) and all(
        n in (-1, m) for n, m in zip(shape, value.shape, strict=True)
    )
    _require(fits, f"session array '{name}' has shape {value.shape}, expected {shape}")
    _require(value.dtype.kind in "biuf", f"session array '{name}' is not numeric")
    return value


def _finite(value: np.ndarray, what: str) -> None:
    _require(bool(np.all(np.isfinite(value))), f"session {what} hold NaN or infinite values")


def _rigid(T: np.ndarray, what: str) -> None:
    _finite(T, what)
    if len(T) == 0:
        return
    R = T[:, :3, :3].astype(np.float64)
    error = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max()
    _require(
        error < ROTATION_TOLERANCE and bool(np.all(np.linalg.det(R) > 0)),
        f"session {what} are not rigid transforms",
    )
    _require(bool(np.all(T[:, 3] == [0, 0, 0, 1])), f"session {what} are not rigid transforms")


def _ids_known(ids: np.ndarray, nodes: set[int], what: str) -> None:
    unknown = set(np.asarray(ids).ravel().tolist()) - nodes
    _require(not unknown, f"session {what} refer to unknown anchor {sorted(unknown)[:3]}")


def _edges(arrays: dict[str, np.ndarray], kind: str, nodes: set[int]) -> None:
    ij = _array(arrays, f"{kind}_ij", (-1, 2))
    T = _array(arrays, f"{kind}_T", (-1, 4, 4))
    cov = _array(arrays, f"{kind}_cov", (-1, 6, 6))
    _require(len(ij) == len(T) == len(cov), f"session {kind} factors are inconsistent")
    _ids_known(ij, nodes, f"{kind} factors")
    _rigid(T, f"{kind} factor poses")
    _finite(cov, f"{kind} covariances")
    if len(cov):
        cov = cov.astype(np.float64)
        symmetric = np.abs(cov - np.swapaxes(cov, 1, 2)).max() <= 1e-6 * max(np.abs(cov).max(), 1)
        lowest = np.linalg.eigvalsh((cov + np.swapaxes(cov, 1, 2)) / 2).min()
        _require(symmetric and lowest > 0, f"session {kind} covariances are not positive definite")


def _parts(parts: Any, frames: int) -> None:
    _require(isinstance(parts, list), "session parts are not a list")
    row = 0
    for part in parts:
        _require(isinstance(part, dict), "session parts are not objects")
        first, rows = part.get("first_row"), part.get("rows")
        _require(
            isinstance(part.get("name"), str) and type(first) is int and type(rows) is int,
            "session parts need a name, first_row and rows",
        )
        _require(first == row and rows >= 0, "session parts do not follow one another")
        row += rows
    _require(not parts or row == frames, f"session parts hold {row} rows for {frames} frames")


def check_session(header: Any, arrays: dict[str, np.ndarray]) -> None:
    """Raise a one-line ``ValueError`` naming the first broken invariant (module docstring)."""
    _require(isinstance(header, dict), "session header is not an object")
    setup = header.get("setup", {})
    _require(isinstance(setup, dict), "session setup is not an object")
    _require(
        isinstance(setup.get("sensor", ""), str) and isinstance(setup.get("session_id", ""), str),
        "session setup's sensor and session_id must be strings",
    )
    node_ids = _array(arrays, "node_ids", (-1,))
    nodes = set(node_ids.tolist())
    _require(len(nodes) == len(node_ids), "session anchor ids are not unique")
    T_W_A = _array(arrays, "T_W_A", (len(node_ids), 4, 4))
    _rigid(T_W_A, "anchor poses")
    frame_submap = _array(arrays, "frame_submap", (-1,))
    frames = len(frame_submap)
    _array(arrays, "frame_pose_A_S", (frames, 7))
    timestamps = _array(arrays, "timestamps", (frames,))
    _finite(timestamps, "timestamps")
    _ids_known(frame_submap, nodes, "frames")
    mirror = _array(arrays, "dataset_mirror", (4, 4)).astype(np.float64)
    _finite(mirror, "dataset mirror")
    _require(np.abs(mirror @ mirror - np.eye(4)).max() < 1e-6, "session dataset mirror is not "
             "its own inverse")  # fmt: skip
    for kind in ("odometry", "loop"):
        _edges(arrays, kind, nodes)
    ids = _array(arrays, "descriptor_ids", (-1,))
    _require(len(set(ids.tolist())) == len(ids), "session descriptor ids are not unique")
    _ids_known(ids, nodes, "descriptors")
    _array(arrays, "descriptor_planar", (len(ids),))
    offsets = _array(arrays, "descriptor_offsets", (len(ids) + 1,))
    positions = _array(arrays, "descriptor_positions", (-1, 3))
    _array(arrays, "descriptor_bits", (len(positions), 32))
    _finite(positions, "descriptor positions")
    _require(
        offsets[0] == 0 and bool(np.all(np.diff(offsets) >= 0)) and offsets[-1] == len(positions),
        "session descriptor offsets disagree with the descriptors",
    )
    up_ids = _array(arrays, "up_ids", (-1,), optional=True)
    up_A = _array(arrays, "up_A", (len(up_ids), 3), optional=True)
    information = _array(arrays, "up_information", (len(up_ids), 3, 3), optional=True)
    _ids_known(up_ids, nodes, "up directions")
    _finite(up_A, "up directions")
    _finite(information, "up information")
    _require(bool(np.all(np.linalg.norm(up_A, axis=1) > 0.5)), "session up directions are not "
             "unit vectors")  # fmt: skip
    _parts(header.get("parts", []), frames)
