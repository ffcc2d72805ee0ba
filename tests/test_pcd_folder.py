"""Folders of ``.pcd`` scans through the ``lidar`` source (pypcd4), on files written here with
pypcd4 itself: every PCD encoding, ``times.txt`` stamps, and one-line errors for broken files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pypcd4 import Encoding, PointCloud

from frontends.errors import DatasetError
from frontends.sources import make_source
from frontends.sources.pcd_folder import read_pcd_points

ENCODINGS = (Encoding.BINARY, Encoding.ASCII, Encoding.BINARY_COMPRESSED)


def _scan(seed: int, n: int = 500) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(-20.0, 20.0, (n, 4)).astype(np.float32)


def _write_pcd(path: Path, scan: np.ndarray, encoding: Encoding = Encoding.BINARY) -> None:
    cloud = PointCloud.from_xyzi_points(scan)
    cloud.save(path, encoding=encoding)


def test_every_encoding_is_read_with_stamps_from_times_txt(tmp_path: Path) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    scans = [_scan(i) for i in range(len(ENCODINGS))]
    for i, (scan, encoding) in enumerate(zip(scans, ENCODINGS, strict=True)):
        _write_pcd(folder / f"{i}.pcd", scan, encoding)
    stamps = 1_565_943_983.5 + np.array([0.0, 5.5, 8.1])
    (tmp_path / "times.txt").write_text("".join(f"{t:.6f}\n" for t in stamps))
    source = make_source("lidar", root=folder, dataloader="generic")
    assert len(source) == len(scans)
    for i, scan in enumerate(scans):
        frame = source[i]
        # ascii keeps about 8 significant digits: micrometres at 20 m
        np.testing.assert_allclose(frame.points, scan[:, :3], atol=1e-4)
        assert frame.timestamp == pytest.approx(stamps[i], abs=1e-5)


def test_stamps_fall_back_to_the_nominal_rate(tmp_path: Path) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    for i in range(2):
        _write_pcd(folder / f"{i}.pcd", _scan(i))
    (tmp_path / "times.txt").write_text("1.0\n2.0\n3.0\n")  # not one stamp per scan: ignored
    source = make_source("lidar", root=folder, dataloader="generic", nominal_rate_hz=10.0)
    assert source[1].timestamp == pytest.approx(0.1)


@pytest.mark.parametrize("cut", ["mid_record", "record_boundary", "header"])
def test_truncated_pcd_is_a_one_line_error(tmp_path: Path, cut: str) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    scan = _scan(0)
    _write_pcd(folder / "0.pcd", scan)
    _write_pcd(folder / "1.pcd", scan)
    data = (folder / "1.pcd").read_bytes()
    header_bytes = len(data) - scan.nbytes
    keep = {
        "mid_record": header_bytes + scan.nbytes // 2 + 3,
        "record_boundary": header_bytes + 16 * 100,
        "header": 60,
    }[cut]
    (folder / "1.pcd").write_bytes(data[:keep])
    source = make_source("lidar", root=folder, dataloader="generic")
    assert len(source[0].points) == len(scan)  # the intact scan still reads
    with pytest.raises(DatasetError) as info:
        source[1]
    message = str(info.value)
    assert "\n" not in message and str(folder / "1.pcd") in message
    assert ("POINTS 500" in message) == (cut == "record_boundary")
    assert "truncated" in message and "re-copy" in message


def test_pcd_without_xyz_is_refused(tmp_path: Path) -> None:
    cloud = PointCloud.from_points(
        _scan(0)[:, :2], fields=("a", "b"), types=(np.float32, np.float32)
    )
    cloud.save(tmp_path / "ab.pcd")
    with pytest.raises(DatasetError, match=r"ab\.pcd: PCD has no field\(s\) x, y, z"):
        read_pcd_points(tmp_path / "ab.pcd")
