"""Keyframing: consecutive frames grouped into submaps that share an anchor pose.

A submap is opened by a frame (its *anchor*, ``T_W_A`` = that frame's pose) and closed when the
sensor has travelled, turned or counted past the limits of
:class:`~slam.algorithm.submap_config.SubmapConfig`
relative to the anchor, or (``max_surface_views``) when the submap covers a given multiple of the
largest surface one of its frames saw: every submap is stored for life, and each boundary between
submaps stores about one view of surface twice, so closing by new surface rather than by time
bounds the map's storage overlap.

Points of every frame are moved into the anchor frame ``A`` with the odometry pose relative to the
anchor and kept voxel-downsampled; a closed submap is what the neural map encodes once and later
moves as a whole, and what loop closure matches.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from kiss_icp.voxelization import voxel_down_sample

from common.geometry import rotation_angle_rad, transform_points
from common.normals import estimate_normals
from common.voxel_keys import point_voxel_keys
from frontends.frame import Frame, point_ranges_m
from slam.algorithm.submap_config import SubmapConfig
from slam.algorithm.voxel_grid import column_voxel_groups, voxel_downsample

SURFACE_CELL_FACTOR = 4
"""Surface coverage (``max_surface_views``) is counted in cells of this many ``map_voxel_m``."""


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
    """A keyframing decision (:meth:`KeyframeDecisions.decide`).

    Attributes:
        closing: the submap the frame closes (its points still to be finished by
            :meth:`SubmapPoints.absorb`), or None.
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
            empty = {"normals": None, "colors": None, "point_times": None}
            keyframe = replace(frame, points=np.zeros((0, 3)), **empty)
        self._current = SubmapRecord(
            submap_id=self._next_id,
            frame_indices=[],
            T_W_A_odometry=T_W_S,
            travelled_m=self._travelled_m,
            keyframe=keyframe,
        )
        self._next_id += 1


class PointChunks:
    """Points in the anchor frame with their normals and viewpoints, as frames add them (each
    averaged on the map grid), averaged together once more than ``compact_every`` are held."""

    def __init__(self, voxel_m: float, compact_every: int) -> None:
        self.voxel_m = voxel_m
        self.compact_every = compact_every
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._count = 0

    def add(self, part: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        self._parts.append(part)
        self._count += len(part[0])
        if len(self._parts) > 1 and self._count > self.compact_every:
            self.compacted()

    def compacted(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Everything held, averaged on the grid (None when empty)."""
        if len(self._parts) > 1:
            stacked = [np.concatenate(rows) for rows in zip(*self._parts, strict=True)]
            self._parts = [voxel_downsample(self.voxel_m, *stacked)]
            self._count = len(self._parts[0][0])
        return self._parts[0] if self._parts else None


class SubmapPoints:
    """The open submap's points in its anchor frame, and the closing of a submap (normals, loop
    cloud): the half of keyframing that the pipeline's submap worker runs, in the order the
    :class:`KeyframeDecisions` were taken."""

    def __init__(self, cfg: SubmapConfig, for_map: bool = True) -> None:
        """``for_map``: the points are for the neural map, averaged on ``map_voxel_m`` (far ones
        on ``far_map_voxel_m``), and points without normals of their own (LiDAR) get normals
        when a submap closes. False (a localisation-only run, which registers the points alone):
        averaged on ``localise_voxel_m``, and their normals are zero where the source has
        none."""
        self.cfg = cfg
        self.for_map = for_map
        if for_map:
            self._voxel_m = cfg.map_voxel_m
            self._far_voxel_m = cfg.far_map_voxel_m or cfg.map_voxel_m
        else:
            self._voxel_m = self._far_voxel_m = cfg.localise_voxel_m or cfg.map_voxel_m
        self.placed = False
        """The run is placed in a stored map: a localisation-only submap then takes frames
        ``localise_scan_spacing_m`` apart only (until then its submaps are matched to the whole
        map, and sparser ones were measured to be placed wrongly)."""
        self._reset_points()

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
        if frame is not None and step.T_A_S is not None and self._takes(step.T_A_S):
            self._accumulate(frame, step.T_A_S)
        return closed

    def _takes(self, T_A_S: np.ndarray) -> bool:
        """Whether a frame at ``T_A_S`` adds its points: always, but in a placed
        localisation-only run only once the sensor moved or turned enough since the last frame
        that did."""
        spacing_m = self.cfg.localise_scan_spacing_m
        last = self._last_taken_T_A_S
        spaced = self.placed and not self.for_map and spacing_m is not None
        if spaced and last is not None:
            moved_m = float(np.linalg.norm(T_A_S[:3, 3] - last[:3, 3]))
            cos_turn = (np.trace(last[:3, :3].T @ T_A_S[:3, :3]) - 1.0) / 2.0
            turned_deg = float(np.degrees(np.arccos(np.clip(cos_turn, -1.0, 1.0))))
            if moved_m < spacing_m and turned_deg < self.cfg.localise_scan_turn_deg:
                return False
        self._last_taken_T_A_S = T_A_S
        return True

    def _reset_points(self) -> None:
        """Empty the point buffers for a new submap."""
        self._near = PointChunks(self._voxel_m, self.cfg.compact_every_points)
        self._far = PointChunks(self._far_voxel_m, self.cfg.compact_every_points)
        self._has_normals = True
        self._surface_keys = np.zeros(0, dtype=np.int64)
        self._view_surface = 0
        self._last_taken_T_A_S: np.ndarray | None = None

    def _accumulate(self, frame: Frame, T_A_S: np.ndarray) -> None:
        """Add a frame's points within the range limits: those within ``loop_max_range_m`` and
        those beyond it each averaged on their grid (gathered straight from the frame's points,
        with one range per point)."""
        points_S = np.asarray(frame.points, dtype=np.float64)
        ranges = point_ranges_m(points_S)
        keep = (ranges >= self.cfg.min_range_m) & (ranges <= self.cfg.max_range_m)
        split_m = self.cfg.loop_max_range_m
        if split_m is None or split_m >= self.cfg.max_range_m:
            parts = [(self._near, keep)]
        else:
            near = ranges <= split_m
            parts = [(self._near, keep & near), (self._far, keep & ~near)]
        normals_S = frame.normals
        if normals_S is not None:
            normals_S = np.asarray(normals_S, dtype=np.float64)
        for chunks, rows in parts:
            normals = None if normals_S is None else np.compress(rows, normals_S, axis=0)
            self._add(chunks, np.compress(rows, points_S, axis=0), normals, T_A_S)

    def _add(
        self, chunks: PointChunks, points_S: np.ndarray, normals_S: np.ndarray | None, T_A_S
    ) -> None:
        """Average a frame's points on the map grid in the anchor frame, into ``chunks``."""
        if len(points_S) == 0:
            return
        if normals_S is None:
            self._has_normals = False
            if self.for_map:
                points_A = self._scan_voxel_means(points_S, T_A_S, chunks.voxel_m)
            else:  # registered alone: a point of each voxel serves, at half the cost
                points_A = voxel_down_sample(transform_points(T_A_S, points_S), chunks.voxel_m)
            normals_A = np.zeros_like(points_A)
        else:
            points_A = transform_points(T_A_S, points_S)
            normals_A = normals_S @ T_A_S[:3, :3].T
            points_A, normals_A = voxel_downsample(chunks.voxel_m, points_A, normals_A)
        if self.for_map:
            viewpoint_A = np.repeat(T_A_S[None, :3, 3], len(points_A), axis=0)
        else:  # only the map's normal estimation looks at viewpoints: none are averaged
            viewpoint_A = np.broadcast_to(np.zeros(3), points_A.shape)
        if self.cfg.max_surface_views is not None:
            self._track_surface(points_A)
        chunks.add((points_A, normals_A, viewpoint_A))

    def _scan_voxel_means(
        self, points_S: np.ndarray, T_A_S: np.ndarray, voxel_m: float
    ) -> np.ndarray:
        """``voxel_downsample(voxel_m, transform_points(T_A_S, points_S))`` on (3, N) coordinate
        rows, where every step runs over contiguous memory: about 2 ms less per 126k-point scan.
        The values agree to rounding (bit for bit with single-threaded OpenBLAS)."""
        columns_A = T_A_S[:3, :3] @ points_S.T
        columns_A += T_A_S[:3, 3:]
        inverse, counts = column_voxel_groups(columns_A, voxel_m)
        sums = [np.bincount(inverse, weights=row, minlength=len(counts)) for row in columns_A]
        return np.stack(sums, axis=1) / counts[:, None]

    def _track_surface(self, points_A: np.ndarray) -> None:
        """Grow the set of surface cells the submap covers, and its largest single view."""
        cells = np.unique(point_voxel_keys(points_A, SURFACE_CELL_FACTOR * self.cfg.map_voxel_m))
        self._surface_keys = np.union1d(self._surface_keys, cells)
        self._view_surface = max(self._view_surface, len(cells))

    def _close(self, sub: SubmapRecord) -> SubmapRecord:
        near, far = self._near.compacted(), self._far.compacted()
        if near is not None or far is not None:
            if near is not None:
                sub.loop_points_A = voxel_down_sample(near[0], self.cfg.loop_voxel_m).astype(
                    np.float32
                )
            if far is None:
                points_A, normals_A, viewpoint_A = near
            else:
                parts = [part for part in (near, far) if part is not None]
                stacked = [np.concatenate(rows) for rows in zip(*parts, strict=True)]
                points_A, normals_A, viewpoint_A = voxel_downsample(self._voxel_m, *stacked)
            if self._has_normals:
                length = np.linalg.norm(normals_A, axis=1)
                valid = length > 0.5
                normals_A = normals_A / np.maximum(length, 1e-12)[:, None]
            elif not self.for_map:
                valid = np.ones(len(points_A), dtype=bool)
            else:
                normals_A, valid = estimate_normals(
                    points_A,
                    viewpoint_A,
                    num_neighbours=self.cfg.normal_neighbours,
                    max_radius_m=self.cfg.normal_radius_m,
                )
            points_A, normals_A = points_A[valid], normals_A[valid]
            cap = self.cfg.max_map_points
            if cap is not None and len(points_A) > cap:
                rng = np.random.default_rng(sub.submap_id)
                keep = np.sort(rng.choice(len(points_A), cap, replace=False))
                points_A, normals_A = points_A[keep], normals_A[keep]
            sub.points_A = points_A
            sub.normals_A = normals_A
        self._reset_points()
        return sub


class Keyframer:
    """Groups frames into submaps and accumulates their points in the anchor frame, in one
    thread: :class:`KeyframeDecisions` and :class:`SubmapPoints` together."""

    def __init__(self, cfg: SubmapConfig) -> None:
        self.cfg = cfg
        self.decisions = KeyframeDecisions(cfg)
        self.points = SubmapPoints(cfg)

    @property
    def decides_from_poses(self) -> bool:
        """See :attr:`KeyframeDecisions.decides_from_poses`."""
        return self.decisions.decides_from_poses

    def add(
        self, frame: Frame, T_W_S: np.ndarray
    ) -> tuple[SubmapRecord | None, SubmapRecord, np.ndarray]:
        """Add a frame with its odometry pose (:meth:`KeyframeDecisions.decide`, then
        :meth:`SubmapPoints.absorb`).

        Returns ``(closed, current, T_A_S)``: the submap this frame closed (or None), the submap
        the frame now belongs to (a new one when it opened one), and the frame's pose relative
        to that submap's anchor.
        """
        step = self.decisions.decide(frame, T_W_S, self.points.surface_full)
        closed = self.points.absorb(step, frame)
        assert step.current is not None and step.T_A_S is not None
        return closed, step.current, step.T_A_S

    def finish(self) -> SubmapRecord | None:
        """Close the open submap (end of the sequence)."""
        step = self.decisions.decide_finish()
        return None if step is None else self.points.absorb(step, None)
