"""The source interface.

A source is a random-access sequence of :class:`~frontends.frame.Frame`. Concrete sources live in
one module each; :data:`frontends.sources.SOURCES` names them.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

from frontends.errors import DatasetError
from frontends.frame import Frame

SensorKind = Literal["lidar", "rgbd"]


class Source(ABC):
    """A recorded sequence.

    Subclasses set ``sensor`` and implement ``__len__`` and ``_load`` (frame ``i`` of the
    selected range). Frame slicing (``frames=slice(a, b, step)``) is handled here.
    """

    sensor: ClassVar[SensorKind]

    dataset_mirror: ClassVar[np.ndarray | None] = None
    """A 4x4 reflection ``M`` when the loader works in a mirrored copy of the dataset's frames
    (ICL-NUIM); poses are written back in the dataset's frame as ``M T M``."""

    def __init__(self, name: str, frames: slice | None = None) -> None:
        self.name = name
        self._frames = frames or slice(None)
        self._indices: np.ndarray | None = None

    @abstractmethod
    def _num_raw_frames(self) -> int:
        """Number of frames on disk, before slicing."""

    @abstractmethod
    def _load(self, raw_index: int) -> Frame:
        """Load frame ``raw_index`` (index into the unsliced sequence)."""

    def _raw_gt_poses(self) -> np.ndarray | None:
        """(N_raw, 4, 4) ground-truth T_W_S of every frame on disk (rows of NaN for frames
        without one), or None."""
        return None

    def data_choices(self) -> dict[str, Any]:
        """Settings the source chose from the data itself, with their evidence (a run writes
        them into ``metrics.json``'s ``input``); none by default."""
        return {}

    @property
    def indices(self) -> np.ndarray:
        """Raw indices of the selected frames."""
        if self._indices is None:
            self._indices = np.arange(self._num_raw_frames())[self._frames]
            if len(self._indices) == 0:
                raise DatasetError(
                    f"{self.name}: frame range {self._frames} selects no frames out of "
                    f"{self._num_raw_frames()}; pass a range inside the sequence"
                )
        return self._indices

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> Frame:
        if not 0 <= i < len(self):
            raise IndexError(i)
        frame = self._load(int(self.indices[i]))
        frame.index = i
        return frame

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def read_ahead(self, depth: int = 2) -> Iterator[Frame]:
        """The frames in order, the next ``depth`` of them loaded on a background thread while
        the caller works on the current one (file reads and image decoding release the GIL).

        Frames are loaded one at a time, in order, so a source needs no locking; a frame that
        fails to load raises here, at its turn.
        """
        count = len(self)
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="read-ahead") as pool:
            pending = deque(pool.submit(self.__getitem__, i) for i in range(min(depth, count)))
            following = len(pending)
            try:
                while pending:
                    frame = pending.popleft().result()
                    if following < count:
                        pending.append(pool.submit(self.__getitem__, following))
                        following += 1
                    yield frame
            finally:
                for future in pending:
                    future.cancel()

    @property
    def gt_poses(self) -> np.ndarray | None:
        """(N, 4, 4) ground-truth T_W_S of the selected frames, or None. Frames without a
        ground-truth pose have a row of NaN: score only ``np.isfinite(gt).all(axis=(1, 2))``."""
        raw = self._raw_gt_poses()
        return None if raw is None else raw[self.indices]

    @classmethod
    def to_dataset_frame(cls, poses: np.ndarray) -> np.ndarray:
        """Poses (N, 4, 4) of the loader's world and sensor frames in the dataset's own frames."""
        mirror = cls.dataset_mirror
        return np.asarray(poses) if mirror is None else mirror @ np.asarray(poses) @ mirror

    @property
    def gt_mesh_path(self) -> Path | None:
        """Ground-truth mesh in the world frame of ``gt_poses``, when the dataset has one."""
        return None
