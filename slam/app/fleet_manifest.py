"""The fleet's input files: a manifest (a YAML list of runs) and a sweep (one run and a grid of
``--set`` values), validated by pydantic models that forbid unknown keys.

A manifest entry holds the run command's own fields (``python -m slam.run DATASET [SEQUENCE]
--root ... --frames ... --set ...``) plus the run's ``name``, the folder it gets under
``DIR/runs/``. Errors are one line naming the file and the entry (:class:`ManifestError`).
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError, field_validator

from common.config import Strict
from slam.assembly.config import describe_validation_error
from slam.assembly.datasets import DATASETS

RUN_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]*$"


class ManifestError(ValueError):
    """A manifest or sweep file is invalid; the message is one line naming the file and entry."""


class FleetRun(Strict):
    """One run of a fleet: the fields of ``python -m slam.run`` plus its name."""

    name: str = Field(
        pattern=RUN_NAME_PATTERN,
        description="the run's folder under DIR/runs/ and its log DIR/logs/<name>.log; unique "
        "in the manifest (letters, digits, '.', '_', '-')",
    )
    dataset: str = Field(description="the run command's DATASET, e.g. kitti, demo, lidar")
    sequence: str | None = Field(
        None,
        description='the run command\'s SEQUENCE (e.g. "00", quoted; for lidar and rgbd the '
        "recording's path)",
    )
    root: Path | None = Field(None, description="--root: the dataset's folder")
    config: Path | None = Field(None, description="--config: a YAML config of configs/' format")
    frames: str | None = Field(None, description='--frames A:B[:STEP], e.g. "0:120"')
    odometry: Literal["gt", "kiss-icp", "rgbd"] | None = Field(None, description="--odometry")
    device: Literal["auto", "cpu", "cuda"] | None = Field(None, description="--device")
    dataloader: str | None = Field(None, description="--dataloader (lidar only)")
    topic: str | None = Field(None, description="--topic (lidar only)")
    overrides: dict[str, Any] = Field(
        default_factory=dict,
        alias="set",
        description="--set values, as a mapping of dotted keys (or nested mappings) to values, "
        "e.g. {threads: 1, loop_closure.enabled: false}",
    )

    @field_validator("dataset")
    @classmethod
    def _known_dataset(cls, value: str) -> str:
        if value not in DATASETS:
            raise ValueError(f"unknown dataset; choose one of: {', '.join(DATASETS)}")
        return value

    def set_items(self) -> dict[str, Any]:
        """``overrides`` flattened to dotted keys."""
        return _flatten(self.overrides)


class Sweep(Strict):
    """One recording run under every combination of a grid of ``--set`` values."""

    run: FleetRun = Field(
        description="the recording, as a manifest entry (its name prefixes "
        "each combination's run name)"
    )
    grid: dict[str, list[Any]] = Field(
        min_length=1,
        description="dotted config key -> the values to try; every combination is one run",
    )

    @field_validator("grid")
    @classmethod
    def _non_empty_values(cls, grid: dict[str, list[Any]]) -> dict[str, list[Any]]:
        for key, values in grid.items():
            if not values:
                raise ValueError(f"'{key}' has no value to try")
        return grid

    def combinations(self) -> list[tuple[FleetRun, dict[str, Any]]]:
        """One manifest entry per combination (named ``<name>-<k>``), with its grid values."""
        keys = list(self.grid)
        out = []
        for k, values in enumerate(itertools.product(*(self.grid[key] for key in keys))):
            chosen = dict(zip(keys, values, strict=True))
            overrides = {**self.run.set_items(), **chosen}
            entry = self.run.model_copy(
                update={"name": f"{self.run.name}-{k}", "overrides": overrides}
            )
            out.append((entry, chosen))
        return out


def _flatten(mapping: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in mapping.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            out.update(_flatten(value, dotted + "."))
        else:
            out[dotted] = value
    return out


def _read_yaml(path: Path) -> Any:
    import yaml

    if not path.is_file():
        raise ManifestError(f"{path}: file not found; pass an existing YAML file")
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        raise ManifestError(f"{path}:{where} is not valid YAML; fix the syntax") from None


def _entry_label(index: int, item: Any) -> str:
    name = item.get("name") if isinstance(item, dict) else None
    return f"entry {index + 1}" + (f" (name '{name}')" if isinstance(name, str) else "")


def load_manifest(path: Path) -> list[FleetRun]:
    """The runs of a manifest file, in its order; raises :class:`ManifestError`."""
    data = _read_yaml(path)
    if not isinstance(data, list) or not data:
        raise ManifestError(
            f"{path}: expected a YAML list of runs, e.g. '- {{name: a, dataset: demo}}'"
        )
    runs: list[FleetRun] = []
    for index, item in enumerate(data):
        label = f"{path}: {_entry_label(index, item)}"
        if not isinstance(item, dict):
            raise ManifestError(f"{label}: expected a mapping such as {{name: a, dataset: demo}}")
        try:
            runs.append(FleetRun.model_validate(item))
        except ValidationError as exc:
            raise ManifestError(describe_validation_error(exc, label, FleetRun)) from None
    seen: set[str] = set()
    for index, run in enumerate(runs):
        if run.name in seen:
            raise ManifestError(
                f"{path}: {_entry_label(index, {'name': run.name})}: the name is used by an "
                "earlier entry; give every run its own name"
            )
        seen.add(run.name)
    return runs


def load_sweep(path: Path) -> Sweep:
    """The sweep of a file; raises :class:`ManifestError`."""
    data = _read_yaml(path)
    if not isinstance(data, dict):
        raise ManifestError(
            f"{path}: expected a mapping with 'run' (a manifest entry) and 'grid' (key: [values])"
        )
    try:
        return Sweep.model_validate(data)
    except ValidationError as exc:
        raise ManifestError(describe_validation_error(exc, str(path), Sweep)) from None
