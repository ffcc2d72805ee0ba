"""What an ``.rrd`` recording holds, per entity, read back with Rerun's own reader (used by the
tests and benchmarks to check what a run logged)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class EntityStats:
    """What a recording holds at one entity path (``arrow_bytes``: uncompressed in memory)."""

    rows: int = 0
    static_rows: int = 0
    max_instances: int = 0
    arrow_bytes: int = 0
    components: set[str] = field(default_factory=set)
    timelines: set[str] = field(default_factory=set)


@dataclass
class RecordingSummary:
    """Per-entity contents of an ``.rrd`` file, read back with Rerun's own reader."""

    path: Path
    size_bytes: int
    application_id: str
    num_blueprints: int
    entities: dict[str, EntityStats]

    def rows(self, entity: str) -> int:
        """Number of temporal rows logged at ``entity`` (0 when absent)."""
        stats = self.entities.get(entity)
        return stats.rows if stats is not None else 0


def summarize_recording(path: Path | str) -> RecordingSummary:
    """Load ``path`` with :class:`rerun.chunk.RrdReader` and count rows per entity."""
    import pyarrow.compute as pc
    from rerun.chunk import RrdReader

    path = Path(path)
    reader = RrdReader(path)
    recordings = reader.recordings()
    if not recordings:
        raise ValueError(f"{path}: no recording store in this .rrd file")
    entities: dict[str, EntityStats] = {}
    index_columns = {"rerun.controls.RowId"}
    for chunk in reader.stream(store=recordings[0]):
        entity = chunk.entity_path.lstrip("/")
        stats = entities.setdefault(entity, EntityStats())
        timelines = set(chunk.timeline_names)
        stats.timelines |= timelines
        if chunk.is_static:
            stats.static_rows += chunk.num_rows
        else:
            stats.rows += chunk.num_rows
        batch = chunk.to_record_batch()
        stats.arrow_bytes += batch.nbytes
        for name, column in zip(batch.schema.names, batch.columns, strict=True):
            if name in index_columns or name in timelines:
                continue
            stats.components.add(name)
            if len(column) and hasattr(column, "offsets"):
                lengths = pc.list_value_length(column).to_numpy(zero_copy_only=False)
                lengths = lengths[np.isfinite(lengths.astype(np.float64))]
                if len(lengths):
                    stats.max_instances = max(stats.max_instances, int(lengths.max()))
    return RecordingSummary(
        path=path,
        size_bytes=path.stat().st_size,
        application_id=str(recordings[0].application_id),
        num_blueprints=len(reader.blueprints()),
        entities=entities,
    )
