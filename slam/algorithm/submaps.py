"""Keyframing: consecutive frames grouped into submaps that share an anchor pose.

A submap is opened by a frame (its *anchor*, ``T_W_A`` = that frame's pose) and closed when the
sensor has travelled, turned or counted past the limits of
:class:`~slam.algorithm.config.SubmapConfig`
relative to the anchor, or (``max_surface_views``) when the submap covers a given multiple of the
largest surface one of its frames saw: every submap is stored for life, and each boundary between
submaps stores about one view of surface twice, so closing by new surface rather than by time
bounds the map's storage overlap.

Points of every frame are moved into the anchor frame ``A`` with the odometry pose relative to the
anchor and kept voxel-downsampled; a closed submap is what the neural map encodes once and later
moves as a whole, and what loop closure matches.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from kiss_icp.voxelization import voxel_down_sample
from pydantic import Field

from common.config import Strict
from common.geometry import rotation_angle_rad, transform_points
from common.normals import estimate_normals
from common.voxel_keys import KEY_LIMIT, point_voxel_keys
from frontends.frame import Frame, point_ranges_m

SURFACE_CELL_FACTOR = 4
"""Surface coverage (``max_surface_views``) is counted in cells of this many ``map_voxel_m``."""


DENSE_GROUPING_CELLS_PER_POINT = 8
""":func:`voxel_groups` counts the points into the cells of their bounding box when it holds at
most this many cells per point (one KITTI scan within 30 m at 0.35 m: ~2), and sorts their keys
otherwise (counting costs about as much per cell as sorting per point)."""


class SubmapConfig(Strict):
    """Keyframing: when a submap closes and how its points are kept."""

    max_distance_m: float = Field(
        2.0, gt=0, description="close the submap when the sensor is this far from the anchor"
    )
    max_rotation_deg: float = Field(
        30.0, gt=0, description="close the submap when the sensor turned this much from the anchor"
    )
    max_frames: int = Field(
        30, ge=1, le=100_000, description="close the submap after this many frames; at most 100,000"
    )
    max_surface_views: float | None = Field(
        None,
        gt=1.0,
        description=(
            "close the submap once the surface it covers (distinct cells of 4 x map_voxel_m) "
            "exceeds this multiple of the largest surface one of its frames saw. Consecutive "
            "submaps share about one view of surface, so this bounds the storage overlap factor "
            "near 1 + 1/max_surface_views however slowly the sensor moves, where a frame count "
            "stores a lingering camera's view again every max_frames frames. None: off"
        ),
    )
    min_range_m: float = Field(0.1, ge=0, description="points nearer to the sensor are dropped")
    max_range_m: float = Field(8.0, gt=0, description="points farther from the sensor are dropped")
    map_voxel_m: float = Field(
        0.02,
        ge=0.001,
        description="points of a submap are averaged on a grid of this size before encoding (at "
        "least 1 mm)",
    )
    loop_voxel_m: float = Field(
        0.05,
        ge=0.001,
        description="grid size of the coarse submap cloud used for loop closure (at least 1 mm)",
    )
    compact_every_points: int = Field(
        400_000,
        ge=1000,
        le=100_000_000,
        description="re-average the accumulated points once this many are buffered; at most "
        "100,000,000",
    )
    normal_neighbours: int = Field(
        12,
        ge=4,
        le=256,
        description="neighbours of the PCA normal fit (sources without normals); at most 256",
    )
    normal_radius_m: float | None = Field(
        None, description="ignore normal-fit neighbours farther than this (None: no limit)"
    )
    max_map_points: int | None = Field(
        None,
        ge=100,
        le=100_000_000,
        description="cap on the points a submap encodes (seeded random subset; None: no cap); at "
        "most 100,000,000",
    )
    keep_points: bool = Field(
        False,
        description="keep each submap's points after encoding (for re-encoding experiments)",
    )
    keep_keyframe_images: bool = Field(
        True, description="keep the anchor frame's RGB-D images (needed by RGB-D loop closure)"
    )


def voxel_groups(points: np.ndarray, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The voxel of every point: ``(inverse, counts)``.

    Voxels are numbered in increasing :func:`~common.voxel_keys.point_voxel_keys` order, so
    this equals ``np.unique(point_voxel_keys(points, voxel_size_m), return_inverse=True,
    return_counts=True)[1:]``, and like it raises a ``ValueError`` for points beyond the range
    of voxel keys.
    Where the bounding box of the points holds few enough cells (one LiDAR scan, one submap) the
    points are counted into those cells in linear time instead of sorting their keys, which was
    the largest cost of keyframing a 126k-point scan.
    """
    return _column_voxel_groups(np.asarray(points, dtype=np.float64).T, voxel_size_m)


def _column_voxel_groups(columns: np.ndarray, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`voxel_groups` of points given as (3, N) coordinate rows."""
    grid = [np.floor(column / voxel_size_m).astype(np.int64) for column in columns]
    low = [int(g.min()) for g in grid]
    high = [int(g.max()) for g in grid]
    dims = [h - lo + 1 for lo, h in zip(low, high, strict=True)]
    cells = dims[0] * dims[1] * dims[2]
    inside = min(low) > -KEY_LIMIT and max(high) < KEY_LIMIT
    if not inside or cells > DENSE_GROUPING_CELLS_PER_POINT * columns.shape[1]:
        _, inverse, counts = np.unique(
            point_voxel_keys(columns.T, voxel_size_m), return_inverse=True, return_counts=True
        )
        return inverse.ravel(), counts
    cell = grid[0] - low[0]
    cell *= dims[1]
    cell += grid[1] - low[1]
    cell *= dims[2]
    cell += grid[2] - low[2]
    cell_counts = np.bincount(cell, minlength=cells)
    occupied = np.flatnonzero(cell_counts)
    voxel_of_cell = np.empty(cells, dtype=np.intp)
    voxel_of_cell[occupied] = np.arange(len(occupied))
    return voxel_of_cell[cell], cell_counts[occupied]


def voxel_downsample(
    voxel_size_m: float, points: np.ndarray, *attributes: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Average points (and per-point float attributes) over the voxels of a grid.

    Differs from ``kiss_icp.voxelization.voxel_down_sample`` on purpose: the mean of each voxel
    (less noise for the map and the normals), not its first point, and in key order.

    Returns ``(points, *attributes)`` with one row per occupied voxel, in increasing
    :func:`~common.voxel_keys.point_voxel_keys` order. An attribute that is the same for every
    row (a broadcast array, e.g. one viewpoint per frame) or all zero (LiDAR frames carry no
    normals) is not averaged: its mean is that row.
    """
    if len(points) == 0:
        return (points, *attributes)
    inverse, counts = voxel_groups(points, voxel_size_m)
    out = []
    for array in (points, *attributes):
        if array is not points and (array.strides[0] == 0 or not array.any()):
            out.append(np.repeat(np.asarray(array[:1], dtype=np.float64), len(counts), axis=0))
            continue
        columns = [
            np.bincount(inverse, weights=array[:, k], minlength=len(counts))
            for k in range(array.shape[1])
        ]
        out.append(np.stack(columns, axis=1) / counts[:, None])
    return tuple(out)


@dataclass
class SubmapRecord:
    """A closed (or open) group of frames sharing an anchor.

    Attributes:
        submap_id: 0, 1, ... in order of creation; also the pose-graph node id.
        frame_indices: indices of the frames it holds; the first is the anchor frame.
        T_W_A_odometry: odometry pose of the anchor.
        travelled_m: path length of the odometry trajectory from the first frame to the anchor.
        points_A: (N, 3) map points in the anchor frame, voxel-averaged.
        normals_A: (N, 3) unit normals of ``points_A`` (towards the sensor).
        loop_points_A: (M, 3) float32 coarse cloud in the anchor frame for loop closure: the
            first point of every ``loop_voxel_m`` voxel (``kiss_icp``'s ``voxel_down_sample``).
        keyframe: the anchor frame with its images (RGB-D) or None.
        T_A_S: relative pose of every frame to the anchor (same order as ``frame_indices``).
    """

    submap_id: int
    frame_indices: list[int]
    T_W_A_odometry: np.ndarray
    travelled_m: float
    points_A: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    normals_A: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    loop_points_A: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    keyframe: Frame | None = None
    T_A_S: list[np.ndarray] = field(default_factory=list)


class KeyframeStep(NamedTuple):
    """A keyframing decision (:meth:`Keyframer.decide`).

    Attributes:
        closing: the submap the frame closes (its points still to be finished by
            :meth:`Keyframer.absorb`), or None.
        current: the submap the frame belongs to (None for the end of the sequence).
        T_A_S: the frame's pose relative to that submap's anchor (None at the end).
        opened: the frame opened ``current``.
    """

    closing: SubmapRecord | None
    current: SubmapRecord | None
    T_A_S: np.ndarray | None
    opened: bool


class KeyframeDecisions:
    """Which submap each frame belongs to, decided from poses (and, with ``max_surface_views``,
    whether the open submap's points cover enough surface): the half of keyframing that the
    pipeline's main thread runs. :class:`SubmapPoints` holds the points."""

    def __init__(self, cfg: SubmapConfig) -> None:
        self.cfg = cfg
        self._current: SubmapRecord | None = None
        self._next_id = 0
        self._travelled_m = 0.0
        self._last_T_W_S: np.ndarray | None = None

    @property
    def current(self) -> SubmapRecord | None:
        """The open submap (None before the first frame and after the last)."""
        return self._current

    @property
    def decides_from_poses(self) -> bool:
        """Whether :meth:`decide` needs only poses: without ``max_surface_views`` a submap closes
        by distance, rotation and frame count, so the points can be absorbed later (on a worker
        thread); with it, every :meth:`SubmapPoints.absorb` must run before the next
        :meth:`decide`, which takes its :attr:`SubmapPoints.surface_full`."""
        return self.cfg.max_surface_views is None

    def _should_close(self, T_A_S: np.ndarray, surface_full: bool) -> bool:
        c = self.cfg
        sub = self._current
        assert sub is not None
        if len(sub.frame_indices) >= c.max_frames or surface_full:
            return True
        if np.linalg.norm(T_A_S[:3, 3]) > c.max_distance_m:
            return True
        return np.degrees(rotation_angle_rad(T_A_S[:3, :3])) > c.max_rotation_deg

    def decide(self, frame: Frame, T_W_S: np.ndarray, surface_full: bool = False) -> KeyframeStep:
        """The keyframing decision for a frame: whether it closes the open submap, which submap
        it belongs to and its pose relative to that anchor. ``surface_full``: the open submap's
        points cover ``max_surface_views`` times its largest view (see
        :attr:`decides_from_poses`)."""
        T_W_S = np.asarray(T_W_S, dtype=np.float64)
        if self._last_T_W_S is not None:
            self._travelled_m += float(np.linalg.norm(T_W_S[:3, 3] - self._last_T_W_S[:3, 3]))
        self._last_T_W_S = T_W_S
        closing = None
        if self._current is not None:
            T_A_S = np.linalg.inv(self._current.T_W_A_odometry) @ T_W_S
            if self._should_close(T_A_S, surface_full):
                closing = self._current
                self._current = None
        opened = self._current is None
        if opened:
            self._open(frame, T_W_S)
        sub = self._current
        assert sub is not None
        T_A_S = np.linalg.inv(sub.T_W_A_odometry) @ T_W_S
        sub.frame_indices.append(frame.index)
        sub.T_A_S.append(T_A_S)
        return KeyframeStep(closing, sub, T_A_S, opened)

    def decide_finish(self) -> KeyframeStep | None:
        """The decision that closes the open submap at the end of the sequence (None when there
        is none); absorb it without a frame."""
        if self._current is None:
            return None
        closing, self._current = self._current, None
        return KeyframeStep(closing, None, None, False)

    def _open(self, frame: Frame, T_W_S: np.ndarray) -> None:
        keep_images = frame.depth is not None and self.cfg.keep_keyframe_images
        keyframe = None
        if keep_images:
            keyframe = Frame(
                index=frame.index,
                timestamp=frame.timestamp,
                points=np.zeros((0, 3)),
                depth=frame.depth,
                rgb=frame.rgb,
                intrinsics=frame.intrinsics,
                T_W_S_gt=frame.T_W_S_gt,
                depth_scale=frame.depth_scale,
            )
        self._current = SubmapRecord(
            submap_id=self._next_id,
            frame_indices=[],
            T_W_A_odometry=T_W_S,
            travelled_m=self._travelled_m,
            keyframe=keyframe,
        )
        self._next_id += 1


class SubmapPoints:
    """The open submap's points in its anchor frame, and the closing of a submap (normals, loop
    cloud): the half of keyframing that the pipeline's submap worker runs, in the order the
    :class:`KeyframeDecisions` were taken."""

    def __init__(self, cfg: SubmapConfig) -> None:
        self.cfg = cfg
        self._chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._has_normals = True
        self._accumulated = 0
        self._surface_keys = np.zeros(0, dtype=np.int64)
        self._view_surface = 0

    @property
    def surface_full(self) -> bool:
        """The open submap covers more than ``max_surface_views`` times the largest surface one
        of its frames saw (False without ``max_surface_views``)."""
        views = self.cfg.max_surface_views
        if views is None or self._view_surface == 0:
            return False
        return len(self._surface_keys) > views * self._view_surface

    def absorb(self, step: KeyframeStep, frame: Frame | None) -> SubmapRecord | None:
        """Apply a decision to the points: close the submap it closes (returned, with its
        points, normals and loop cloud), then add the frame's points to its submap. Steps must be
        absorbed in the order they were decided."""
        closed = None
        if step.closing is not None:
            closed = self._close(step.closing)
        if step.opened:
            self._reset_points()
        if frame is not None and step.T_A_S is not None:
            self._accumulate(frame, step.T_A_S)
        return closed

    def _reset_points(self) -> None:
        """Empty the point buffers for a new submap."""
        self._chunks = []
        self._accumulated = 0
        self._has_normals = True
        self._surface_keys = np.zeros(0, dtype=np.int64)
        self._view_surface = 0

    def _frame_points(self, frame: Frame) -> tuple[np.ndarray, np.ndarray | None]:
        points = np.asarray(frame.points, dtype=np.float64)
        ranges = point_ranges_m(points)
        keep = (ranges >= self.cfg.min_range_m) & (ranges <= self.cfg.max_range_m)
        points = np.compress(keep, points, axis=0)
        normals = frame.normals
        if normals is not None:
            normals = np.compress(keep, np.asarray(normals, dtype=np.float64), axis=0)
        return points, normals

    def _accumulate(self, frame: Frame, T_A_S: np.ndarray) -> None:
        points_S, normals_S = self._frame_points(frame)
        if len(points_S) == 0:
            return
        if normals_S is None:
            self._has_normals = False
            points_A = self._scan_voxel_means(points_S, T_A_S)
            normals_A = np.zeros_like(points_A)
        else:
            points_A = transform_points(T_A_S, points_S)
            normals_A = normals_S @ T_A_S[:3, :3].T
            points_A, normals_A = voxel_downsample(self.cfg.map_voxel_m, points_A, normals_A)
        viewpoint_A = np.repeat(T_A_S[None, :3, 3], len(points_A), axis=0)
        if self.cfg.max_surface_views is not None:
            self._track_surface(points_A)
        self._chunks.append((points_A, normals_A, viewpoint_A))
        self._accumulated += len(points_A)
        if len(self._chunks) > 1 and self._accumulated > self.cfg.compact_every_points:
            self._compact()

    def _scan_voxel_means(self, points_S: np.ndarray, T_A_S: np.ndarray) -> np.ndarray:
        """``voxel_downsample(transform_points(T_A_S, points_S))`` computed on (3, N) coordinate
        rows, where every step runs over contiguous memory: about 2 ms less per 126k-point scan.
        The values agree to rounding (bit for bit with single-threaded OpenBLAS)."""
        columns_A = T_A_S[:3, :3] @ points_S.T
        columns_A += T_A_S[:3, 3:]
        inverse, counts = _column_voxel_groups(columns_A, self.cfg.map_voxel_m)
        sums = [np.bincount(inverse, weights=row, minlength=len(counts)) for row in columns_A]
        return np.stack(sums, axis=1) / counts[:, None]

    def _track_surface(self, points_A: np.ndarray) -> None:
        """Grow the set of surface cells the submap covers, and its largest single view."""
        cells = np.unique(point_voxel_keys(points_A, SURFACE_CELL_FACTOR * self.cfg.map_voxel_m))
        self._surface_keys = np.union1d(self._surface_keys, cells)
        self._view_surface = max(self._view_surface, len(cells))

    def _compact(self) -> None:
        if not self._chunks:
            return
        stacked = [np.concatenate(parts) for parts in zip(*self._chunks, strict=True)]
        merged = voxel_downsample(self.cfg.map_voxel_m, *stacked)
        self._chunks = [merged]
        self._accumulated = len(merged[0])

    def _close(self, sub: SubmapRecord) -> SubmapRecord:
        self._compact()
        if self._chunks:
            points_A, normals_A, viewpoint_A = self._chunks[0]
            if self._has_normals:
                length = np.linalg.norm(normals_A, axis=1)
                valid = length > 0.5
                normals_A = normals_A / np.maximum(length, 1e-12)[:, None]
            else:
                normals_A, valid = estimate_normals(
                    points_A,
                    viewpoint_A,
                    num_neighbours=self.cfg.normal_neighbours,
                    max_radius_m=self.cfg.normal_radius_m,
                )
            sub.loop_points_A = voxel_down_sample(points_A, self.cfg.loop_voxel_m).astype(
                np.float32
            )
            points_A, normals_A = points_A[valid], normals_A[valid]
            cap = self.cfg.max_map_points
            if cap is not None and len(points_A) > cap:
                rng = np.random.default_rng(sub.submap_id)
                keep = np.sort(rng.choice(len(points_A), cap, replace=False))
                points_A, normals_A = points_A[keep], normals_A[keep]
            sub.points_A = points_A
            sub.normals_A = normals_A
        self._chunks = []
        return sub


class Keyframer:
    """Groups frames into submaps and accumulates their points in the anchor frame, in one
    thread: :class:`KeyframeDecisions` and :class:`SubmapPoints` together."""

    def __init__(self, cfg: SubmapConfig) -> None:
        self.cfg = cfg
        self.decisions = KeyframeDecisions(cfg)
        self.points = SubmapPoints(cfg)

    @property
    def current(self) -> SubmapRecord | None:
        """The open submap (None before the first frame and after :meth:`finish`)."""
        return self.decisions.current

    @property
    def decides_from_poses(self) -> bool:
        """See :attr:`KeyframeDecisions.decides_from_poses`."""
        return self.decisions.decides_from_poses

    def add(
        self, frame: Frame, T_W_S: np.ndarray
    ) -> tuple[SubmapRecord | None, SubmapRecord, np.ndarray]:
        """Add a frame with its odometry pose (:meth:`decide`, then :meth:`absorb`).

        Returns ``(closed, current, T_A_S)``: the submap this frame closed (or None), the submap
        the frame now belongs to (a new one when it opened one), and the frame's pose relative
        to that submap's anchor.
        """
        step = self.decide(frame, T_W_S)
        closed = self.absorb(step, frame)
        assert step.current is not None and step.T_A_S is not None
        return closed, step.current, step.T_A_S

    def decide(self, frame: Frame, T_W_S: np.ndarray) -> KeyframeStep:
        """The keyframing decision for a frame (:meth:`KeyframeDecisions.decide`)."""
        return self.decisions.decide(frame, T_W_S, self.points.surface_full)

    def decide_finish(self) -> KeyframeStep | None:
        """See :meth:`KeyframeDecisions.decide_finish`."""
        return self.decisions.decide_finish()

    def absorb(self, step: KeyframeStep, frame: Frame | None) -> SubmapRecord | None:
        """See :meth:`SubmapPoints.absorb`."""
        return self.points.absorb(step, frame)

    def finish(self) -> SubmapRecord | None:
        """Close the open submap (end of the sequence)."""
        step = self.decide_finish()
        return None if step is None else self.absorb(step, None)
