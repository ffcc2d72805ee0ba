"""Any LiDAR recording that a ``kiss_icp.datasets`` dataloader reads ("lidar").

The dataloaders of KISS-ICP 1.3 are wrapped, not re-implemented: ``generic`` (a folder of
``.bin/.ply/.xyz/.obj/.off/.stl`` scans), ``rosbag`` (ROS1 ``.bag`` files or a ROS2 bag
folder), ``mcap``, ``ouster`` (``.pcap`` + metadata JSON), ``nuscenes``, ``mulran``, ``ncd``,
``helipr``, ``boreas``, ``apollo``, ``nclt``, ``kitti`` and ``kitti_raw``. One addition: a folder
of ``.npy`` scans (``(N, >=3)`` float arrays) is read with ``numpy.load`` (no pickles), because
KISS-ICP's generic loader does not list ``.npy``. And a ``generic`` folder whose scans are all
``.pcd`` is read with ``pypcd4`` (frontends/sources/pcd_folder.py), not through KISS-ICP's
open3d reader.

What comes through from the dataloader:

- points (``(N, 3)`` float64, sensor frame);
- per-point times for deskewing when the dataloader returns them (PointCloud2 fields ``t``,
  ``time``, ``timestamp``; MulRan, NCD, Boreas, KITTI raw, HeLiPR);
- scan timestamps: ``get_frames_timestamps()`` (bags and MCAP give the message stamps as they are
  read; KITTI its ``times.txt``), ``scan_timestamps`` / ``timestamps`` where the dataloader keeps
  them (nanoseconds are converted to seconds); for a folder of scans, a ``times.txt`` (one
  stamp a line, one line per scan) in the folder or beside it (MulRan's ``times.txt`` next to
  ``scans/``, KITTI's next to ``velodyne/``); else ``index / nominal_rate_hz``;
- ground truth ``gt_poses`` where the dataloader has it; otherwise an optional KITTI (12 values,
  one row per scan) or TUM (``t tx ty tz qx qy qz qw``, matched by timestamp) file given as
  ``gt_poses``.

Bags, MCAP and pcap files can only be read front to back; the source keeps a cursor and rewinds
(``reset()``) when asked for an earlier scan. The dataloaders report problems with ``print`` and
``sys.exit``; both are caught here and turned into a one-line :class:`DatasetError`.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import logging
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from frontends.errors import DatasetError
from frontends.frame import Frame
from frontends.sources._io import fail, load_table, one_line, read_tum_trajectory
from frontends.sources.base import SensorKind, Source
from frontends.sources.pcd_folder import PcdFolder

log = logging.getLogger(__name__)

KISS_DATALOADERS = (
    "generic",
    "rosbag",
    "mcap",
    "ouster",
    "nuscenes",
    "mulran",
    "ncd",
    "helipr",
    "boreas",
    "apollo",
    "nclt",
    "kitti",
    "kitti_raw",
)
"""The kiss_icp.datasets dataloaders this source wraps (KISS-ICP's ``tum`` is RGB-D: use ours)."""

DATALOADERS = (*KISS_DATALOADERS, "npy")

SEQUENTIAL = frozenset({"rosbag", "mcap", "ouster"})
"""Dataloaders that can only be read in order (KISS-ICP's non-jumpable ones)."""

NEEDS_SEQUENCE = frozenset({"kitti", "kitti_raw", "nuscenes", "helipr"})

OPTIONAL_MODULES: dict[str, tuple[tuple[str, ...], str]] = {
    "rosbag": (("rosbags.highlevel",), "rosbag"),
    "mcap": (("mcap.reader", "mcap_ros2.reader"), "mcap"),
    "ouster": (("ouster.sdk",), "ouster"),
    "nuscenes": (("nuscenes",), "nuscenes"),
    "apollo": (("open3d",), "open3d"),
    "ncd": (("pyntcloud",), "pyntcloud"),
}
"""Modules a dataloader imports that this project does not install by default, and the extra of
``pyproject.toml`` that installs them."""

KISS_GENERIC_SUFFIXES = frozenset({"bin", "ply", "xyz", "obj", "off", "stl"})
"""Generic-folder scan formats left to KISS-ICP's generic dataloader (trimesh, numpy)."""

TIMES_FILE = "times.txt"

NANOSECONDS_ABOVE = 1e14
"""Scan stamps larger than this are nanoseconds (1e14 s is far beyond any epoch time)."""


def install_hint(extra: str) -> str:
    return f'pip install "neural-remap-slam[{extra}]" (or: pip install -e ".[{extra}]")'


def check_dataloader_modules(dataloader: str, path: Path) -> None:
    """Raise a one-line DatasetError naming the extra to install when a reader is missing."""
    modules, extra = OPTIONAL_MODULES.get(dataloader, ((), ""))
    for module in modules:
        try:
            importlib.import_module(module)
        except ImportError:
            raise DatasetError(
                f"{path}: the '{dataloader}' dataloader needs the Python module '{module}'; "
                f"{install_hint(extra)}"
            ) from None


class _NpyFolder:
    """A folder of ``.npy`` scans, in natural order, in the shape of a kiss_icp dataloader."""

    def __init__(self, data_dir: Path) -> None:
        import natsort

        self.scan_files = natsort.natsorted(str(p) for p in Path(data_dir).glob("*.npy"))
        if not self.scan_files:
            raise ValueError(f"no .npy scans in {data_dir}")

    def __len__(self) -> int:
        return len(self.scan_files)

    def __getitem__(self, idx: int) -> tuple[np.ndarray, np.ndarray]:
        array = np.load(self.scan_files[idx], allow_pickle=False)
        if array.ndim != 2 or array.shape[1] < 3:
            raise ValueError(
                f"{self.scan_files[idx]}: expected an (N, >=3) array, got {array.shape}"
            )
        return np.asarray(array[:, :3], dtype=np.float64), np.array([])


@contextlib.contextmanager
def _dataloader_errors(path: Path, dataloader: str, what: str):
    """Silence the dataloader's prints; turn its exits and exceptions into one DatasetError."""
    printed = io.StringIO()
    try:
        with contextlib.redirect_stdout(printed):
            yield
    except DatasetError:
        raise
    except (SystemExit, Exception) as exc:  # the dataloaders raise anything, or exit
        said = one_line(printed.getvalue())
        detail = one_line(str(exc)) if not isinstance(exc, SystemExit) else ""
        reason = "; ".join(part for part in (detail, said) if part) or type(exc).__name__
        raise fail(
            path,
            f"kiss_icp '{dataloader}' dataloader could not {what} ({reason[:300]})",
            "check the path, --dataloader and source.lidar.topic/sequence",
        ) from None
    finally:
        for line in printed.getvalue().splitlines():
            if line.strip():
                log.info("%s: %s", dataloader, line.strip())


def open_dataloader(
    dataloader: str, path: Path, *, sequence: str | None = None, topic: str | None = None
) -> Any:
    """The kiss_icp dataloader (or the ``.npy`` folder reader) of ``path``."""
    if dataloader not in DATALOADERS:
        raise DatasetError(
            f"unknown LiDAR dataloader '{dataloader}'; choose one of: {', '.join(DATALOADERS)}"
        )
    if not path.exists():
        raise fail(path, "not found", "pass the recording (a folder, bag or file) to read")
    if dataloader in NEEDS_SEQUENCE and sequence is None:
        raise fail(
            path,
            f"the '{dataloader}' dataloader needs a sequence",
            "pass --set source.lidar.sequence=NAME",
        )
    check_dataloader_modules(dataloader, path)
    with _dataloader_errors(path, dataloader, "open it"):
        if dataloader == "npy":
            return _NpyFolder(path)
        if dataloader == "generic" and _is_pcd_folder(path):
            return PcdFolder(path)
        from kiss_icp.datasets import dataset_factory

        dataset = dataset_factory(dataloader, path, sequence=sequence, topic=topic)
    if dataloader == "mcap":
        dataset.read_point_cloud = _with_field_constants(dataset.read_point_cloud)
    return dataset


def _is_pcd_folder(path: Path) -> bool:
    """A folder holding ``.pcd`` scans and no scan format of KISS-ICP's generic loader."""
    if not path.is_dir():
        return False
    suffixes = {p.suffix.lstrip(".").lower() for p in path.iterdir() if p.is_file()}
    return "pcd" in suffixes and not KISS_GENERIC_SUFFIXES & suffixes


def folder_times_file(path: Path) -> Path | None:
    """``times.txt`` in a scan folder, else beside it, or None."""
    if not path.is_dir():
        return None
    for candidate in (path / TIMES_FILE, path.parent / TIMES_FILE):
        if candidate.is_file():
            return candidate
    return None


POINT_FIELD_TYPES = {
    "INT8": 1,
    "UINT8": 2,
    "INT16": 3,
    "UINT16": 4,
    "INT32": 5,
    "UINT32": 6,
    "FLOAT32": 7,
    "FLOAT64": 8,
}
"""The datatype constants of ``sensor_msgs/PointField``."""


def _with_field_constants(read_point_cloud):
    """KISS-ICP 1.3 names a PointField's datatype by searching ``vars(field)`` for the constants;
    mcap-ros2-support decodes messages into ``__slots__`` classes, where ``vars`` is empty. Hand
    the reader a plain copy of the message whose fields carry the constants."""
    from types import SimpleNamespace

    def read(msg):
        def copy(item, names: tuple[str, ...], **extra) -> SimpleNamespace:
            return SimpleNamespace(**{n: getattr(item, n) for n in names}, **extra)

        field_names = ("name", "offset", "datatype", "count")
        fields = [copy(f, field_names, **POINT_FIELD_TYPES) for f in msg.fields]
        names = ("header", "height", "width", "is_bigendian", "point_step", "row_step", "data")
        plain = copy(msg, names, fields=fields)
        plain.is_dense = getattr(msg, "is_dense", True)
        return read_point_cloud(plain)

    return read


class LidarSource(Source):
    """A LiDAR recording read by a ``kiss_icp.datasets`` dataloader (see the module docstring).

    Args:
        root: the recording: a folder of scans, a bag file or folder, an ``.mcap``/``.pcap``
            file, or a dataset root, as the dataloader expects.
        dataloader: one of :data:`DATALOADERS` (``generic`` by default).
        sequence: sequence name for the dataloaders that need one (kitti, kitti_raw, nuscenes,
            helipr).
        topic: ``sensor_msgs/PointCloud2`` topic of a bag or MCAP file (needed when it has more
            than one).
        frames: optional slice of scans.
        gt_poses: optional ground truth when the dataloader has none: a KITTI pose file (one row
            per scan) or a TUM trajectory (associated by scan timestamp), in the sensor frame.
        nominal_rate_hz: scan rate used for timestamps when the dataloader gives none.
        max_range_m: drop points farther than this (None keeps all).
        max_time_difference_s: TUM ground truth: largest stamp gap when associating.
    """

    sensor: ClassVar[SensorKind] = "lidar"

    def __init__(
        self,
        root: str | Path,
        dataloader: str = "generic",
        *,
        sequence: str | None = None,
        topic: str | None = None,
        frames: slice | None = None,
        gt_poses: str | Path | None = None,
        nominal_rate_hz: float = 10.0,
        max_range_m: float | None = None,
        max_time_difference_s: float = 0.02,
    ) -> None:
        self.path = Path(root).expanduser()
        name = self.path.stem or self.path.name
        super().__init__(f"lidar-{dataloader}-{name}", frames)
        self.dataloader = dataloader
        self.nominal_rate_hz = nominal_rate_hz
        self.max_range_m = max_range_m
        self.dataset = open_dataloader(dataloader, self.path, sequence=sequence, topic=topic)
        self._count = len(self.dataset)
        if self._count == 0:
            raise fail(self.path, "the recording holds no scans", "check the path and topic")
        self._sequential = dataloader in SEQUENTIAL
        self._cursor = 0  # next scan a sequential dataloader returns
        self._stamps: dict[int, float] = {}
        self._static_stamps: np.ndarray | None = None
        self._max_dt = max_time_difference_s
        self._gt = self._dataloader_gt()
        if self._gt is None and gt_poses is not None:
            self._gt = self._read_gt_file(Path(gt_poses).expanduser())

    # --- ground truth -----------------------------------------------------------------------

    def _dataloader_gt(self) -> np.ndarray | None:
        poses = getattr(self.dataset, "gt_poses", None)
        if poses is None:
            return None
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != self._count:
            log.warning("%s: dataloader ground truth has shape %s; ignored", self.name, poses.shape)
            return None
        return poses

    def _read_gt_file(self, path: Path) -> np.ndarray:
        """KITTI rows (one per scan), or a TUM trajectory associated by scan timestamp (a bag is
        read once for its stamps) -> (N, 4, 4)."""
        from frontends.sources._io import associate
        from frontends.sources.kitti import read_kitti_poses

        try:
            stamps, poses = read_tum_trajectory(path)
        except DatasetError:
            poses = read_kitti_poses(path)
            if len(poses) != self._count:
                raise fail(
                    path,
                    f"{len(poses)} poses for {self._count} scans",
                    "give one KITTI pose per scan, or a TUM trajectory with timestamps",
                ) from None
            return poses
        scan_stamps = self.scan_timestamps()
        matches = associate(scan_stamps, stamps, self._max_dt)
        if len(matches) != self._count:
            raise fail(
                path,
                f"{self._count - len(matches)} of {self._count} scans have no pose within "
                f"{self._max_dt} s",
                "pass the ground truth of this recording (or raise max_time_difference_s)",
            )
        return poses[[j for _, j in matches]]

    def _raw_gt_poses(self) -> np.ndarray | None:
        return self._gt

    # --- timestamps -------------------------------------------------------------------------

    def scan_timestamps(self) -> np.ndarray:
        """(N_raw,) scan timestamps in seconds (reads a sequential recording once if needed)."""
        stamps = self._static_timestamps()
        if stamps is not None:
            return stamps
        for i in range(self._count):
            if i not in self._stamps:
                self._load(i)
        return np.array([self._stamps[i] for i in range(self._count)])

    def _static_timestamps(self) -> np.ndarray | None:
        """Stamps the dataloader knows without reading the scans, or None."""
        if self._sequential:
            return None
        for attribute in ("scan_timestamps", "timestamps"):
            values = getattr(self.dataset, attribute, None)
            if values is not None and len(values) == self._count:
                return _seconds(np.asarray(values, dtype=np.float64).reshape(-1))
        getter = getattr(self.dataset, "get_frames_timestamps", None)
        if getter is not None:
            with _dataloader_errors(self.path, self.dataloader, "read its timestamps"):
                values = np.asarray(getter(), dtype=np.float64).reshape(-1)
            if len(values) == self._count:
                return _seconds(values)
        times_file = folder_times_file(self.path)
        if times_file is not None:
            values = load_table(times_file, 1, "one scan timestamp a line").reshape(-1)
            if len(values) == self._count:
                log.info("%s: scan timestamps from %s", self.name, times_file)
                return _seconds(values)
            log.warning(
                "%s: %s has %d stamps for %d scans; ignored",
                self.name,
                times_file,
                len(values),
                self._count,
            )
        return np.arange(self._count, dtype=np.float64) / self.nominal_rate_hz

    # --- scans ------------------------------------------------------------------------------

    def _num_raw_frames(self) -> int:
        return self._count

    def _read(self, raw_index: int) -> Any:
        if not self._sequential:
            return self.dataset[raw_index]
        if raw_index < self._cursor:
            self.dataset.reset()
            self._cursor = 0
        item = None
        while self._cursor <= raw_index:
            item = self.dataset[self._cursor]
            stamps = getattr(self.dataset, "get_frames_timestamps", lambda: [])()
            if len(stamps):
                self._stamps[self._cursor] = float(_seconds(np.asarray(stamps[-1:]))[0])
            else:
                self._stamps[self._cursor] = self._cursor / self.nominal_rate_hz
            self._cursor += 1
        return item

    def _load(self, raw_index: int) -> Frame:
        with _dataloader_errors(self.path, self.dataloader, f"read scan {raw_index}"):
            item = self._read(raw_index)
        points, times = item if isinstance(item, tuple) else (item, None)
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        times = None if times is None or len(times) == 0 else np.asarray(times, np.float64)
        if times is not None and len(times) != len(points):
            log.warning(
                "%s: scan %d has %d point times for %d points; not deskewed",
                self.name,
                raw_index,
                len(times),
                len(points),
            )
            times = None
        finite = np.isfinite(points).all(axis=1) & (np.abs(points).sum(axis=1) > 0)
        if self.max_range_m is not None:
            finite &= np.linalg.norm(points, axis=1) <= self.max_range_m
        points = points[finite]
        times = None if times is None else times[finite]
        if len(points) == 0:
            raise fail(self.path, f"scan {raw_index} holds no valid point", "check the recording")
        if self._sequential:
            stamp = self._stamps[raw_index]
        else:
            stamps = self._stamps_cache()
            stamp = float(stamps[raw_index])
        gt = self._gt
        return Frame(
            index=raw_index,
            timestamp=stamp,
            points=points,
            point_times=times,
            T_W_S_gt=None if gt is None else gt[raw_index].copy(),
        )

    def _stamps_cache(self) -> np.ndarray:
        if self._static_stamps is None:
            self._static_stamps = self._static_timestamps()
        return self._static_stamps


def _seconds(values: np.ndarray) -> np.ndarray:
    """Stamps in seconds (nanosecond stamps are recognised by their size)."""
    if len(values) and np.nanmax(np.abs(values)) > NANOSECONDS_ABOVE:
        return values * 1e-9
    return values
