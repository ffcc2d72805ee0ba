"""Rows of a Rerun recording held back and sent as columns.

``RecordingStream.log`` builds an archetype in Python and crosses into Rerun once per entity and
frame, which is most of what a recording costs the main thread per frame. :class:`ColumnBuffer`
keeps each entity's rows instead (their components and times) and sends them with one
``send_columns`` call per entity every :data:`FLUSH_FRAMES` frames and, when a viewer watches the
run live, every :data:`LIVE_FLUSH_S` seconds (it lags at most that much), and on
:meth:`ColumnBuffer.flush`.
The rows are the ones ``log`` would have written, on the same timelines: ``frame``,
``sensor_time`` and Rerun's own ``log_time``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

FLUSH_FRAMES = 30
"""Held rows are sent at least this often (in frames): each ``send_columns`` call costs about
0.3 ms on the main thread whatever its length."""
LIVE_FLUSH_S = 0.5
"""... and, for a live viewer, at least this often in seconds."""


@dataclass
class _Rows:
    """One entity's held rows: their times, and per component one value or batch per row."""

    archetype: Any
    frames: list[int] = field(default_factory=list)
    sensor_times_s: list[float] = field(default_factory=list)
    log_times_ns: list[int] = field(default_factory=list)
    batches: dict[str, list[np.ndarray]] = field(default_factory=dict)
    values: dict[str, list[Any]] = field(default_factory=dict)


class ColumnBuffer:
    """Rows of a :class:`rerun.RecordingStream` held back per entity and sent as columns.

    Args:
        rec: the recording the columns are sent to.
        live: a viewer watches the recording as it is made: rows are sent at least every
            :data:`LIVE_FLUSH_S` seconds too.
    """

    def __init__(self, rec: Any, live: bool) -> None:
        self.rec = rec
        self.max_delay_s = LIVE_FLUSH_S if live else math.inf
        self.sensor_time_is_epoch = False
        """``sensor_time`` is a timestamp (epoch seconds), else a duration."""
        self._frame = 0
        self._sensor_time_s = 0.0
        self._rows: dict[str, _Rows] = {}
        self._flushed_frame = 0
        self._flushed_at = time.monotonic()

    def set_time(self, frame_index: int, sensor_time_s: float) -> None:
        """The time of the rows added from now on; sends the held rows when they are due."""
        self._frame = frame_index
        self._sensor_time_s = sensor_time_s
        if (
            frame_index - self._flushed_frame >= FLUSH_FRAMES
            or time.monotonic() - self._flushed_at >= self.max_delay_s
        ):
            self.flush()

    def add(
        self,
        entity: str,
        archetype: Any,
        batches: dict[str, np.ndarray] | None = None,
        **values: Any,
    ) -> None:
        """A row of ``archetype`` at ``entity`` at the current time: ``batches`` are components
        with one entry per instance (a point cloud's positions and colours, all of one length;
        arrays, or lists such as line strips), ``values`` components with one value per row (a
        translation, an image blob)."""
        rows = self._rows.get(entity)
        if rows is None:
            rows = self._rows[entity] = _Rows(archetype)
        rows.frames.append(self._frame)
        rows.sensor_times_s.append(self._sensor_time_s)
        rows.log_times_ns.append(time.time_ns())
        for name, batch in (batches or {}).items():
            rows.batches.setdefault(name, []).append(batch)
        for name, value in values.items():
            rows.values.setdefault(name, []).append(value)

    def flush(self) -> None:
        """Send every held row: one ``send_columns`` call per entity."""
        import rerun as rr

        clock = "timestamp" if self.sensor_time_is_epoch else "duration"
        for entity, rows in self._rows.items():
            indexes = [  # arrays: Rerun converts a list element by element
                rr.TimeColumn("frame", sequence=np.array(rows.frames, np.int64)),
                rr.TimeColumn("sensor_time", **{clock: np.array(rows.sensor_times_s)}),
                rr.TimeColumn("log_time", timestamp=np.array(rows.log_times_ns, "datetime64[ns]")),
            ]
            columns = []
            if rows.batches:
                lengths = [len(batch) for batch in next(iter(rows.batches.values()))]
                joined = {name: _join(batches) for name, batches in rows.batches.items()}
                columns.extend(rows.archetype.columns(**joined).partition(lengths))
            if rows.values:
                stacked = {name: _stack(values) for name, values in rows.values.items()}
                columns.extend(rows.archetype.columns(**stacked))
            self.rec.send_columns(entity, indexes=indexes, columns=columns)
        self._rows.clear()
        self._flushed_frame = self._frame
        self._flushed_at = time.monotonic()


def _join(batches: list[Any]) -> Any:
    """Per-row batches as one: arrays concatenated, lists (e.g. of line strips) chained."""
    if isinstance(batches[0], np.ndarray):
        return np.concatenate(batches)
    return [item for batch in batches for item in batch]


def _stack(values: list[Any]) -> Any:
    """One value per row as a column: arrays stacked along a first axis, anything else as is."""
    return np.stack(values) if isinstance(values[0], np.ndarray) else values
