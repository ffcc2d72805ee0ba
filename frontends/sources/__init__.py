"""Data sources, one module per dataset family, chosen by name from :data:`SOURCES`."""

from __future__ import annotations

from frontends.errors import DatasetError
from frontends.sources.base import Source
from frontends.sources.generated import GeneratedSource
from frontends.sources.kitti import KittiSource
from frontends.sources.lidar import LidarSource
from frontends.sources.replica import ReplicaSource
from frontends.sources.sevenscenes import SevenScenesSource
from frontends.sources.tum import IclSource, TumSource

SOURCES: dict[str, type[Source]] = {
    "generated": GeneratedSource,
    "kitti": KittiSource,
    "lidar": LidarSource,
    "tum": TumSource,
    "icl": IclSource,
    "replica": ReplicaSource,
    "7scenes": SevenScenesSource,
}
"""Every source by the name ``source.dataset`` gives it; the keyword arguments each takes from a
run's config are in :data:`slam.assembly.datasets.SOURCE_OPTIONS`."""


def source_class(name: str) -> type[Source]:
    """The source registered as ``name``; an unknown name is a one-line :class:`DatasetError`."""
    if name not in SOURCES:
        raise DatasetError(f"unknown source '{name}'; choose one of: {', '.join(SOURCES)}")
    return SOURCES[name]


def make_source(name: str, **kwargs) -> Source:
    """Build the source registered as ``name`` (keyword arguments go to its constructor)."""
    return source_class(name)(**kwargs)


__all__ = ["SOURCES", "Source", "make_source", "source_class"]
