"""KITTI odometry LiDAR sequences.

Layout (the official one)::

    root/sequences/NN/velodyne/NNNNNN.bin   float32 x, y, z, reflectance per point
    root/sequences/NN/calib.txt             needs the 'Tr:' line (LiDAR -> left camera)
    root/sequences/NN/times.txt             one timestamp (s) per scan
    root/poses/NN.txt                       optional ground truth, 12 values a row, camera frame

Ground truth is returned in the LiDAR frame, ``T_lidar = inv(Tr) @ T_cam @ Tr``, exactly as
``kiss_icp.datasets.kitti`` does. Reflectance is not part of :class:`Frame`; read it with
:meth:`KittiSource.reflectance` or :func:`read_kitti_bin`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from frontends.errors import DatasetError
from frontends.frame import Frame
from frontends.sources._io import fail, load_table, require_dir, require_file
from frontends.sources.base import SensorKind, Source
from frontends.sources.beam_correction import (
    CorrectionSetting,
    choose_correction,
    correct_vertical_angle,
)

BYTES_PER_POINT = 16  # four float32


def read_kitti_bin(path: str | Path) -> np.ndarray:
    """Read a KITTI Velodyne ``.bin`` scan -> (N, 4) float32 ``x, y, z, reflectance``.

    Raises DatasetError when the file is missing, truncated (size not a multiple of 16 bytes),
    empty, or holds non-finite coordinates.
    """
    path = Path(path)
    require_file(path, "a KITTI .bin scan (float32 x, y, z, reflectance)")
    size = path.stat().st_size
    if size % BYTES_PER_POINT:
        raise fail(
            path,
            f"size {size} bytes is not a multiple of {BYTES_PER_POINT} (truncated scan)",
            "re-extract or re-download the scan",
        )
    if size == 0:
        raise fail(path, "scan is empty", "remove it or re-extract the sequence")
    scan = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    # a float64 sum of float32 values cannot overflow, so it is finite exactly when every value
    # is: a sixth of the cost of testing the coordinates, needed only when it is not (reflectance)
    if not np.isfinite(scan.sum(dtype=np.float64)) and not np.isfinite(scan[:, :3]).all():
        raise fail(path, "scan holds NaN/inf coordinates", "re-extract or re-download the scan")
    return scan


def read_kitti_calib_tr(path: Path) -> np.ndarray:
    """The 4x4 ``Tr`` (LiDAR -> left camera) of a KITTI ``calib.txt``."""
    from kiss_icp.datasets.kitti import KITTIOdometryDataset

    require_file(path, "KITTI calib.txt with a 'Tr:' line")
    try:
        calib = KITTIOdometryDataset.read_calib_file(str(path))
    except ValueError as err:
        raise fail(path, f"malformed calibration ({err})", "use the official calib.txt") from None
    values = calib.get("Tr")
    if values is None or values.size != 12:
        raise fail(path, "no 'Tr:' line with 12 values", "use the official odometry calib.txt")
    tr = np.eye(4)
    tr[:3, :4] = np.asarray(values, dtype=np.float64).reshape(3, 4)
    return tr


def read_kitti_poses(path: Path) -> np.ndarray:
    """KITTI pose file (12 values a row) -> (N, 4, 4) float64, in the file's frame."""
    table = load_table(path, 12, "KITTI poses, 12 values a row")
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :4] = table.reshape(-1, 3, 4)
    return poses


class KittiSource(Source):
    """One KITTI odometry sequence.

    Args:
        root: dataset root holding ``sequences/`` (and optionally ``poses/``).
        sequence: sequence id, e.g. ``"00"`` or ``"7"``.
        frames: optional slice of scans.
        correct_vertical_angle: apply KISS-ICP's KITTI intrinsic correction (a 0.205 deg
            elevation fix for the HDL-64E calibration) as ``kiss_icp.datasets.kitti`` does:
            ``"auto"`` decides from the road in the scans
            (:func:`frontends.sources.beam_correction.choose_correction`), True or False is kept
            (with a warning where the road disagrees). ``correction`` holds the choice.
        max_range_m: drop points farther than this (None keeps all).
    """

    sensor: ClassVar[SensorKind] = "lidar"

    def __init__(
        self,
        root: str | Path,
        sequence: str,
        frames: slice | None = None,
        *,
        correct_vertical_angle: CorrectionSetting = "auto",
        max_range_m: float | None = None,
    ) -> None:
        root = Path(root).expanduser()
        seq = str(sequence).zfill(2)
        super().__init__(f"kitti-{seq}", frames)
        self.root = root
        self.sequence = seq
        self.max_range_m = max_range_m

        require_dir(root, "the KITTI odometry root holding sequences/ and poses/")
        self.sequence_dir = require_dir(
            root / "sequences" / seq, f"sequences/{seq}/ with velodyne/, calib.txt and times.txt"
        )
        velodyne = require_dir(self.sequence_dir / "velodyne", "NNNNNN.bin LiDAR scans")
        self.scan_files = sorted(velodyne.glob("*.bin"))
        if not self.scan_files:
            raise fail(velodyne, "no .bin scans found", "extract data_odometry_velodyne here")
        self.T_cam_lidar = read_kitti_calib_tr(self.sequence_dir / "calib.txt")

        times_file = self.sequence_dir / "times.txt"
        self.timestamps = load_table(times_file, 1, "one timestamp per scan")[:, 0]
        if len(self.timestamps) != len(self.scan_files):
            raise fail(
                times_file,
                f"{len(self.timestamps)} timestamps for {len(self.scan_files)} scans",
                "use the times.txt of this sequence and a complete velodyne/ folder",
            )

        self._gt: np.ndarray | None = None
        poses_file = root / "poses" / f"{seq}.txt"
        if poses_file.is_file():
            T_cam = read_kitti_poses(poses_file)
            if len(T_cam) != len(self.scan_files):
                raise fail(
                    poses_file,
                    f"{len(T_cam)} poses for {len(self.scan_files)} scans",
                    "use the poses file of this sequence and a complete velodyne/ folder",
                )
            self._gt = camera_to_lidar_poses(T_cam, self.T_cam_lidar)
        self.correction = choose_correction(
            correct_vertical_angle, self._raw_points, len(self.indices), str(velodyne)
        )
        self.correct_vertical_angle = self.correction.apply

    def _num_raw_frames(self) -> int:
        return len(self.scan_files)

    def _raw_points(self, i: int) -> np.ndarray | None:
        """The raw points of selected frame ``i``, uncorrected, for choosing the correction;
        None where the scan cannot be read (reported when its frame is)."""
        try:
            return self._read(int(self.indices[i]))[:, :3]
        except DatasetError:
            return None

    def _raw_gt_poses(self) -> np.ndarray | None:
        return self._gt

    def data_choices(self) -> dict[str, Any]:
        return {"kitti_vertical_angle_correction": self.correction.record()}

    def reflectance(self, i: int) -> np.ndarray:
        """(N,) float32 reflectance of selected frame ``i``, in the order of its points."""
        return self._read(int(self.indices[i]))[:, 3]

    def _read(self, raw_index: int) -> np.ndarray:
        """(N, 4) float32 scan of ``raw_index`` after the range filter."""
        scan = read_kitti_bin(self.scan_files[raw_index])
        if self.max_range_m is not None:
            scan = scan[np.linalg.norm(scan[:, :3], axis=1) <= self.max_range_m]
            if len(scan) == 0:
                raise fail(
                    self.scan_files[raw_index],
                    f"no point within max_range_m={self.max_range_m}",
                    "raise max_range_m",
                )
        return scan

    def _load(self, raw_index: int) -> Frame:
        scan = self._read(raw_index)
        if self.correct_vertical_angle:
            points = correct_vertical_angle(scan[:, :3])
        else:  # column by column: a sixth of the cost of converting the (N, 3) view at once
            points = np.empty((len(scan), 3))
            for k in range(3):
                points[:, k] = scan[:, k]
        gt = self._gt
        return Frame(
            index=raw_index,
            timestamp=float(self.timestamps[raw_index]),
            points=points,
            T_W_S_gt=None if gt is None else gt[raw_index].copy(),
        )


def camera_to_lidar_poses(T_cam: np.ndarray, T_cam_lidar: np.ndarray) -> np.ndarray:
    """KITTI camera-frame poses -> LiDAR-frame poses: ``inv(Tr) @ T_cam @ Tr``."""
    return np.linalg.inv(T_cam_lidar) @ T_cam @ T_cam_lidar
