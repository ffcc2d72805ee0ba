"""The dataset registry: every name of the command line, the source it reads, its default config,
and the keyword arguments that source takes from a run's config.

Adding a dataset family means a source module in ``frontends/sources`` (listed in
:data:`frontends.sources.SOURCES`), its options function in :data:`SOURCE_OPTIONS`, a
:class:`DatasetEntry` and a YAML file in ``configs/``; ``tests/test_datasets.py`` checks that the
four agree.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from slam.assembly.config import RunConfig


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


def frame_slice(text: str | None) -> slice | None:
    """``"A:B[:STEP]"`` as a slice (validated by the runner), None for all frames."""
    if text is None:
        return None
    parts = [int(p) if p.strip() else None for p in text.split(":")]
    return slice(*parts)


def _sequence_options(cfg: RunConfig) -> dict[str, Any]:
    src = cfg.source
    return {"root": src.root, "sequence": src.sequence, "frames": frame_slice(src.frames)}


def _depth_options(cfg: RunConfig) -> dict[str, Any]:
    return {**_sequence_options(cfg), "depth_options": cfg.source.depth.model_dump()}


def _kitti_options(cfg: RunConfig) -> dict[str, Any]:
    return {**_sequence_options(cfg), **cfg.source.kitti.model_dump()}


def _icl_options(cfg: RunConfig) -> dict[str, Any]:
    return {**_depth_options(cfg), "max_difference": cfg.source.tum.max_time_difference_s}


def _tum_options(cfg: RunConfig) -> dict[str, Any]:
    tum = cfg.source.tum
    return {
        **_icl_options(cfg),
        "intrinsics": None if tum.intrinsics is None else tum.intrinsics.model_dump(),
        "depth_scale": tum.depth_scale,
        "allow_outside_paths": tum.allow_outside_paths,
    }


def _lidar_options(cfg: RunConfig) -> dict[str, Any]:
    src = cfg.source
    return {
        **src.lidar.model_dump(exclude={"scale_from_first_scan"}),  # the runner applies it
        "root": src.root,
        "frames": frame_slice(src.frames),
        "max_time_difference_s": src.tum.max_time_difference_s,
    }


def _generated_options(cfg: RunConfig) -> dict[str, Any]:
    """Every ``generated`` field a sequence of its ``kind`` uses (the image size for RGB-D, the
    street and trajectory for LiDAR)."""
    src, g = cfg.source, cfg.generated
    if g.kind == "rgbd":
        options = g.model_dump(include={"kind", "num_frames", "seed", "width", "height"})
        loader_options = {"depth_options": src.depth.model_dump()}
    else:
        options = g.model_dump(exclude={"width", "height"})
        loader_options = {"max_range_m": src.kitti.max_range_m}
    frames = frame_slice(src.frames)
    return {**options, "root": src.root, "frames": frames, "loader_options": loader_options}


SOURCE_OPTIONS: dict[str, Callable[[RunConfig], dict[str, Any]]] = {
    "generated": _generated_options,
    "kitti": _kitti_options,
    "lidar": _lidar_options,
    "tum": _tum_options,
    "icl": _icl_options,
    "replica": _depth_options,
    "7scenes": _depth_options,
}
"""The keyword arguments of each source in :data:`frontends.sources.SOURCES`, from a run's
config."""


def source_kwargs(cfg: RunConfig) -> dict[str, Any]:
    """Keyword arguments of ``make_source`` for the configured dataset."""
    return SOURCE_OPTIONS[cfg.source.dataset](cfg)
