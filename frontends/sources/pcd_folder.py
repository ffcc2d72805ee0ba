"""A folder of PCL ``.pcd`` scans (ascii, binary or binary_compressed), read with ``pypcd4``.

KISS-ICP's generic dataloader reads ``.pcd`` only through open3d, a large optional install; the
``lidar`` source reads a folder whose scans are all ``.pcd`` with this class instead (same shape as
a kiss_icp dataloader: ``len()`` and ``[i] -> (points, times)``). Only ``x y z`` are used; per-point
times are not read (their units differ between drivers), so PCD scans are taken as already
de-skewed, as exported keyframes are.

A file whose data holds fewer records than its header's ``POINTS`` (a truncated copy) or whose
header cannot be parsed raises a one-line :class:`~frontends.errors.DatasetError` naming the file.
Trailing bytes after ``POINTS`` records are ignored (some exporters pad the file).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from frontends.sources._io import fail, one_line

PCD_SUFFIX = ".pcd"


def pcd_scan_files(folder: Path) -> list[Path]:
    """The ``.pcd`` files of ``folder`` in natural order (``2.pcd`` before ``10.pcd``)."""
    import natsort

    return [Path(p) for p in natsort.natsorted(str(p) for p in folder.glob(f"*{PCD_SUFFIX}"))]


def read_pcd_points(path: Path) -> np.ndarray:
    """``(POINTS, 3)`` float64 ``x y z`` of one PCD file: exactly the header's POINTS records."""
    from pypcd4 import PointCloud

    fix = "re-copy the file from the recording, or remove it from the folder"
    try:
        cloud = PointCloud.from_path(path)
    except Exception as exc:  # pypcd4 raises pydantic, numpy and lzf errors alike
        raise fail(path, f"truncated or corrupt PCD ({one_line(exc)[:200]})", fix) from None
    metadata = cloud.metadata
    if len(cloud.pc_data) != metadata.points:
        raise fail(
            path,
            f"truncated PCD: the header says POINTS {metadata.points}, the data holds "
            f"{len(cloud.pc_data)} records",
            fix,
        )
    missing = [name for name in ("x", "y", "z") if name not in metadata.fields]
    if missing:
        raise fail(path, f"PCD has no field(s) {', '.join(missing)}", "export x, y and z")
    return np.asarray(cloud.numpy(("x", "y", "z")), dtype=np.float64).reshape(-1, 3)


class PcdFolder:
    """A folder of ``.pcd`` scans in natural order, in the shape of a kiss_icp dataloader."""

    def __init__(self, data_dir: Path) -> None:
        self.scan_files = pcd_scan_files(Path(data_dir))
        if not self.scan_files:
            raise fail(data_dir, "no .pcd scans in the folder", "pass a folder of .pcd files")

    def __len__(self) -> int:
        return len(self.scan_files)

    def __getitem__(self, idx: int) -> tuple[np.ndarray, np.ndarray]:
        return read_pcd_points(self.scan_files[idx]), np.array([])
