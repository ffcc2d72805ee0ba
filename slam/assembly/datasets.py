"""The dataset names of the command line: which source and default config each one uses."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DatasetEntry:
    """A dataset name of the command line: its source, default config and whether it needs data.

    ``path_argument``: the positional argument is the recording's path (not a sequence name).
    """

    source: str
    config: str
    needs_root: bool
    needs_sequence: bool
    path_argument: bool = False


DATASETS: dict[str, DatasetEntry] = {
    "kitti": DatasetEntry("kitti", "kitti", True, True),
    "icl": DatasetEntry("icl", "icl", True, True),
    "tum": DatasetEntry("tum", "tum", True, True),
    "replica": DatasetEntry("replica", "replica", True, True),
    "7scenes": DatasetEntry("7scenes", "7scenes", True, True),
    "demo": DatasetEntry("generated", "demo", False, False),
    "generated-lidar": DatasetEntry("generated", "generated-lidar", False, False),
    "lidar": DatasetEntry("lidar", "lidar", False, True, path_argument=True),
    "rgbd": DatasetEntry("tum", "tum", False, True, path_argument=True),
}
