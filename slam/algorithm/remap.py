"""Remapping: submaps whose anchor moved in the pose graph are moved in the neural map.

After every optimisation, each submap's anchor estimate is compared with the pose the map
currently holds it at. When the translation or the rotation angle of the difference exceeds the
thresholds of :class:`~slam.algorithm.config.RemapConfig`, the submap is removed from the global
map,
transformed from its *original* encoding to the new pose and fused back
(:meth:`mapping.neural_map.NeuralMap.move`). Small differences are left alone: they are below
what the voxel grid resolves and moving them would only cost time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from pydantic import Field

from common.config import Strict
from common.geometry import relative_motion


class RemapConfig(Strict):
    """Remapping of submaps whose anchor moved after an optimisation."""

    enabled: bool = Field(True, description="move submaps in the neural map after optimisation")
    translation_threshold_m: float = Field(
        0.005, ge=0, description="remap a submap whose anchor moved more than this"
    )
    rotation_threshold_deg: float = Field(
        0.25, ge=0, description="remap a submap whose anchor turned more than this"
    )


@dataclass
class RemapEvent:
    """One remapping pass.

    Attributes:
        frame_index: the frame at which it ran (-1 at the end of the run).
        num_checked: submaps compared.
        moved_ids: submaps moved.
        seconds: wall time of the moves.
        max_translation_m: largest anchor translation among the moved submaps.
        max_rotation_deg: largest anchor rotation among the moved submaps.
    """

    frame_index: int
    num_checked: int
    moved_ids: list[int] = field(default_factory=list)
    seconds: float = 0.0
    max_translation_m: float = 0.0
    max_rotation_deg: float = 0.0

    @property
    def num_moved(self) -> int:
        return len(self.moved_ids)


class Remapper:
    """Moves the submaps of a neural map to the latest pose-graph estimates."""

    def __init__(self, cfg: RemapConfig, neural_map) -> None:
        self.cfg = cfg
        self.neural_map = neural_map
        self.events: list[RemapEvent] = []

    def needs_move(
        self, T_W_A_current: np.ndarray, T_W_A_new: np.ndarray
    ) -> tuple[bool, float, float]:
        """Whether the anchor moved beyond a threshold: ``(move, translation_m, rotation_deg)``."""
        translation, rotation = relative_motion(T_W_A_current, T_W_A_new)
        move = (
            translation > self.cfg.translation_threshold_m
            or rotation > self.cfg.rotation_threshold_deg
        )
        return move, translation, rotation

    def apply(self, submaps: dict, T_W_A: dict[int, np.ndarray], frame_index: int) -> RemapEvent:
        """Move every submap of ``submaps`` (``{id: Submap}``) whose anchor in ``T_W_A`` moved."""
        event = RemapEvent(frame_index=frame_index, num_checked=0)
        if not self.cfg.enabled:
            return event
        start = time.perf_counter()
        for submap_id, submap in submaps.items():
            if submap_id not in T_W_A:
                continue
            event.num_checked += 1
            move, translation, rotation = self.needs_move(submap.T_W_A, T_W_A[submap_id])
            if not move:
                continue
            self.neural_map.move(submap, T_W_A[submap_id])
            event.moved_ids.append(submap_id)
            event.max_translation_m = max(event.max_translation_m, translation)
            event.max_rotation_deg = max(event.max_rotation_deg, rotation)
        event.seconds = time.perf_counter() - start
        if event.moved_ids:
            self.events.append(event)
        return event
