"""Small readers shared by the sources, and the common RGB-D frame assembly.

Every reader turns a bad file into a one-line :class:`~frontends.errors.DatasetError` that names
the file and says what is expected.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from frontends.depth import depth_to_points
from frontends.errors import DatasetError
from frontends.frame import Frame, Intrinsics
from frontends.sources.base import SensorKind, Source

log = logging.getLogger(__name__)


def one_line(text: str) -> str:
    """Collapse whitespace so an error message is always a single line."""
    return " ".join(str(text).split())


def fail(path: Path | str, problem: str, fix: str) -> DatasetError:
    """A one-line DatasetError: '<path>: <problem>; <fix>'."""
    return DatasetError(one_line(f"{path}: {problem}; {fix}"))


def require_dir(path: Path, what: str) -> Path:
    """Return ``path`` if it is a folder, else raise saying which folder is expected."""
    if not path.is_dir():
        raise fail(
            path, f"folder not found (expected {what})", "check --root and the sequence name"
        )
    return path


def require_file(path: Path, what: str) -> Path:
    """Return ``path`` if it is a file, else raise saying which file is expected."""
    if not path.is_file():
        raise fail(path, f"file not found (expected {what})", "check --root and the sequence name")
    return path


def load_table(path: Path, columns: int, what: str) -> np.ndarray:
    """Read a whitespace table of floats (``#`` comments allowed) with exactly ``columns`` columns.

    Returns an (N, columns) float64 array; raises on ragged rows, non-numbers or an empty file.
    """
    require_file(path, what)
    rows: list[list[float]] = []
    with path.open() as f:
        for line_no, line in enumerate(f, 1):
            text = line.split("#", 1)[0].replace(",", " ").strip()
            if not text:
                continue
            tokens = text.split()
            if len(tokens) != columns:
                raise fail(
                    path,
                    f"line {line_no} has {len(tokens)} values, expected {columns} ({what})",
                    "fix or regenerate the file",
                )
            try:
                rows.append([float(t) for t in tokens])
            except ValueError as err:
                raise fail(path, f"line {line_no} is not numeric ({err})", "fix the file") from None
    if not rows:
        raise fail(path, f"file holds no rows ({what})", "fix or regenerate the file")
    return np.asarray(rows, dtype=np.float64)


def read_stamped_paths(path: Path) -> tuple[np.ndarray, list[str]]:
    """Read a TUM list file (``rgb.txt``/``depth.txt``): lines ``timestamp relative/path``."""
    require_file(path, "a TUM list file with lines 'timestamp path'")
    stamps: list[float] = []
    names: list[str] = []
    with path.open() as f:
        for line_no, line in enumerate(f, 1):
            text = line.split("#", 1)[0].strip()
            if not text:
                continue
            tokens = text.split()
            try:
                stamps.append(float(tokens[0]))
                names.append(tokens[1])
            except (ValueError, IndexError):
                raise fail(
                    path, f"line {line_no} is not 'timestamp path'", "fix the list file"
                ) from None
    if not stamps:
        raise fail(path, "list file is empty", "regenerate it from the image folder")
    return np.asarray(stamps), names


def pose_from_translation_quaternion(values: np.ndarray) -> np.ndarray:
    """(N, 7) rows ``tx ty tz qx qy qz qw`` -> (N, 4, 4) float64 transforms."""
    from scipy.spatial.transform import Rotation

    values = np.atleast_2d(values)
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(values[:, 3:7]).as_matrix()
    poses[:, :3, 3] = values[:, :3]
    return poses


def read_tum_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory (``t tx ty tz qx qy qz qw``) -> (stamps (N,), T (N, 4, 4))."""
    table = load_table(path, 8, "TUM trajectory rows 't tx ty tz qx qy qz qw'")
    quat_norm = np.linalg.norm(table[:, 4:8], axis=1)
    if np.any(np.abs(quat_norm - 1.0) > 1e-2):
        row = int(np.argmax(np.abs(quat_norm - 1.0)))
        raise fail(path, f"row {row + 1} has a non-unit quaternion", "fix the trajectory file")
    return table[:, 0], pose_from_translation_quaternion(table[:, 1:])


def associate(
    stamps_a: np.ndarray, stamps_b: np.ndarray, max_difference: float = 0.02
) -> list[tuple[int, int]]:
    """Match timestamps as TUM's ``associate.py`` does.

    All pairs closer than ``max_difference`` are sorted by time difference and taken greedily so
    that each stamp is used at most once. Returns ``(index_a, index_b)`` pairs sorted by
    ``index_a``.
    """
    a = np.asarray(stamps_a, dtype=np.float64)
    b = np.asarray(stamps_b, dtype=np.float64)
    order_b = np.argsort(b, kind="stable")
    b_sorted = b[order_b]
    lo = np.searchsorted(b_sorted, a - max_difference, side="left")
    hi = np.searchsorted(b_sorted, a + max_difference, side="right")
    candidates: list[tuple[float, int, int]] = []
    for i, (start, stop) in enumerate(zip(lo, hi, strict=True)):
        for j_sorted in range(start, stop):
            diff = abs(a[i] - b_sorted[j_sorted])
            if diff < max_difference:
                candidates.append((diff, i, int(order_b[j_sorted])))
    candidates.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    matches: list[tuple[int, int]] = []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            matches.append((i, j))
    matches.sort()
    return matches


def read_rgb(path: Path) -> np.ndarray:
    """Read a colour image -> (H, W, 3) uint8 RGB."""
    import cv2

    require_file(path, "a colour image")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise fail(path, "unreadable colour image", "replace the corrupt file")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)  # ~20x faster than copying image[..., ::-1]


def read_depth_png(
    path: Path,
    scale: float,
    invalid_values: tuple[int, ...] = (0,),
    max_valid_m: float | None = None,
) -> np.ndarray:
    """Read a 16-bit depth PNG -> (H, W) float32 metres (``value / scale``), 0 where invalid.

    Raises when the file is not a single-channel uint16 image or holds no valid depth at all.
    """
    import cv2

    require_file(path, "a 16-bit depth PNG")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise fail(path, "unreadable depth image", "replace the corrupt file")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise fail(
            path,
            f"depth image is {raw.dtype} with shape {raw.shape}, expected single-channel uint16",
            "use the dataset's original 16-bit depth PNGs",
        )
    depth = raw.astype(np.float32) / np.float32(scale)
    for value in invalid_values:  # a comparison per value: several times faster than np.isin
        depth[raw == value] = 0.0
    if max_valid_m is not None:
        depth[depth > max_valid_m] = 0.0
    if not np.any(depth > 0):
        raise fail(path, "depth image has no valid pixel (all zero/invalid)", "remove this frame")
    return depth


def frame_number(path: Path, pattern: str) -> int:
    """The integer captured by ``pattern`` (a regex with one group) in ``path.name``."""
    match = re.fullmatch(pattern, path.name)
    if match is None:
        raise fail(path, f"file name does not match {pattern!r}", "rename it as the dataset does")
    return int(match.group(1))


class DepthOptions(BaseModel):
    """How depth images are lifted to points (see :func:`frontends.depth.depth_to_points`)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    min_depth_m: float = Field(0.1, gt=0, description="Nearest valid depth (metres).")
    max_depth_m: float = Field(10.0, gt=0, description="Farthest valid depth (metres).")
    stride: int = Field(
        1, ge=1, le=64, description="Keep every stride-th pixel in rows and columns.; at most 64"
    )
    normal_step_px: int = Field(
        2,
        ge=1,
        le=64,
        description="Pixel offset of the neighbours used to estimate normals.; at most 64",
    )
    max_points: int | None = Field(
        None,
        ge=1,
        le=100_000_000,
        description="Seeded random subset of at most this many points per frame.; at most "
        "100,000,000",
    )

    @classmethod
    def of(cls, value: DepthOptions | dict | None) -> DepthOptions:
        """Accept an instance, a plain dict (e.g. from YAML) or None (defaults)."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        try:
            return cls.model_validate(value)
        except ValidationError as err:
            raise DatasetError(one_line(f"depth_options: {err}")) from None


@dataclass(frozen=True)
class RgbdFrames:
    """The RGB-D frames on disk: per frame a timestamp, a colour and a depth image."""

    stamps: np.ndarray  # (N,) frame timestamps (seconds)
    rgb: list[Path]
    depth: list[Path]


class RgbdSource(Source):
    """Shared frame assembly of the RGB-D sources.

    Subclasses set ``depth_scale``/``invalid_depth_values``/``intrinsics`` and their frames
    with :meth:`_set_frames`.
    """

    sensor: ClassVar[SensorKind] = "rgbd"
    depth_scale: float
    invalid_depth_values: tuple[int, ...] = (0,)
    intrinsics: Intrinsics

    def __init__(
        self, name: str, frames: slice | None, depth_options: DepthOptions | dict | None
    ) -> None:
        super().__init__(name, frames)
        self.depth_options = DepthOptions.of(depth_options)

    def _set_frames(self, frames: RgbdFrames, gt: np.ndarray | None) -> None:
        """The frames on disk and their (N, 4, 4) ground-truth poses (None: none)."""
        self._rgbd_frames = frames
        self._gt = gt

    def _num_raw_frames(self) -> int:
        return len(self._rgbd_frames.stamps)

    def _raw_gt_poses(self) -> np.ndarray | None:
        return self._gt

    def _load(self, raw_index: int) -> Frame:
        depth_path, rgb_path = self._rgbd_frames.depth[raw_index], self._rgbd_frames.rgb[raw_index]
        depth = read_depth_png(depth_path, self.depth_scale, self.invalid_depth_values)
        self._check_shape(depth_path, depth.shape)
        rgb = read_rgb(rgb_path)
        if rgb.shape[:2] != depth.shape:
            raise fail(
                rgb_path,
                f"colour image is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                f"{depth.shape[1]}x{depth.shape[0]}",
                "use colour and depth images of the same size",
            )
        opts = self.depth_options
        cloud = depth_to_points(
            depth, self.intrinsics, rgb=rgb, seed=raw_index, **opts.model_dump()
        )
        if len(cloud) == 0:
            raise fail(
                depth_path,
                f"no valid depth in [{opts.min_depth_m}, {opts.max_depth_m}] m",
                "remove this frame or widen min_depth_m/max_depth_m",
            )
        gt = self._raw_gt_poses()
        T_W_S_gt = None if gt is None else gt[raw_index].copy()
        if T_W_S_gt is not None and not np.isfinite(T_W_S_gt).all():
            T_W_S_gt = None  # this frame has no ground-truth pose
        return Frame(
            index=raw_index,
            timestamp=float(self._rgbd_frames.stamps[raw_index]),
            points=cloud.points,
            normals=cloud.normals,
            colors=cloud.colors,
            depth=depth,
            rgb=rgb,
            intrinsics=self.intrinsics,
            T_W_S_gt=T_W_S_gt,
            depth_scale=float(self.depth_scale),
        )

    def _check_shape(self, path: Path, shape: tuple[int, ...]) -> None:
        expected = (self.intrinsics.height, self.intrinsics.width)
        if shape != expected:
            raise fail(
                path,
                f"depth image is {shape[1]}x{shape[0]}, the intrinsics say "
                f"{expected[1]}x{expected[0]}",
                "pass matching intrinsics for this dataset",
            )
