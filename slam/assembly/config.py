"""Configuration of a run: one pydantic model per part, composed into :class:`RunConfig`.

Every model forbids unknown keys, so a typo in a YAML file is an error that names the key rather
than a silently ignored setting. :func:`load_run_config` reads a YAML file and turns validation
errors into a one-line :class:`ConfigError`.
"""

from __future__ import annotations

import argparse
import difflib
import re
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, ValidationError, field_validator

from common.config import Strict
from frontends.odometry.kiss import KissIcpConfig
from frontends.odometry.rgbd import RgbdOdometryConfig
from mapping.config import MapConfig
from slam.algorithm.config import PipelineConfig
from slam.algorithm.graph.config import PoseGraphConfig
from slam.algorithm.loops.config import LoopClosureConfig
from slam.algorithm.merge.config import LocaliseConfig
from slam.algorithm.remap import RemapConfig
from slam.algorithm.submap_config import SubmapConfig
from slam.assembly.source_config import GeneratedConfig, SourceConfig

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"


class ConfigError(ValueError):
    """A configuration file or value is invalid; the message is one line naming the key."""


class OdometryConfig(Strict):
    """The odometry front-end."""

    method: Literal["auto", "gt", "kiss-icp", "rgbd"] = Field(
        "auto", description="'auto' picks kiss-icp for LiDAR and rgbd for RGB-D sources"
    )
    kiss_icp: KissIcpConfig = Field(
        default_factory=KissIcpConfig, description="KISS-ICP options (method kiss-icp)"
    )
    rgbd: RgbdOdometryConfig = Field(
        default_factory=RgbdOdometryConfig, description="OpenCV RGB-D options (method rgbd)"
    )
    kiss_icp_start_scans: int = Field(
        8,
        ge=0,
        le=1000,
        description="kiss-icp: register this many scans after the first to their predecessor by "
        "point-to-plane ICP before KISS-ICP takes over: KISS-ICP starts from rest and cannot "
        "see motion along blank walls (frontends/odometry/kiss.py; 30 scans of the generated "
        "sparse street: along-track error 13.8 m alone, 1.4 m with 4, 0.8 m with 8); 0: off; at "
        "most 1000",
    )
    child_process: bool = Field(
        True,
        description="kiss-icp with map_worker on: run KISS-ICP in a child process (Linux), "
        "because its bindings hold the GIL through each registration and so stall the worker "
        "threads (frontends/odometry/child_process.py); results are the same either way",
    )
    child_reply_timeout_s: float = Field(
        120.0,
        gt=0,
        description="kiss-icp in a child process: the longest one reply of the child may take "
        "(a registration takes 30-100 ms, starting it a few seconds); a child that takes longer "
        "is stopped and the run ends with one line, as when the child dies",
    )


class VizConfig(Strict):
    """Where the Rerun recording goes and how much it holds."""

    mode: Literal["rrd", "spawn", "connect", "serve", "none"] = Field(
        "rrd",
        description="write an .rrd file, spawn a viewer, connect to one, serve the web viewer "
        "over HTTP (and write the .rrd), or log nothing",
    )
    rrd_path: Path | None = Field(
        None, description="recording file (default: recording.rrd in the run folder)"
    )
    connect_url: str | None = Field(None, description="viewer URL for mode 'connect'")
    serve_grpc_port: int = Field(
        9876, ge=1, le=65535, description="mode 'serve': port of the gRPC server viewers read"
    )
    serve_web_port: int = Field(
        9090, ge=1, le=65535, description="mode 'serve': port of the web viewer page (HTTP)"
    )
    serve_bind_ip: str = Field(
        "127.0.0.1",
        description="mode 'serve': address both servers listen on (localhost: reach them "
        "through an SSH port forward; 0.0.0.0 exposes them to the network)",
    )
    serve_linger_s: float | None = Field(
        None,
        ge=0,
        description="mode 'serve': keep serving this long after the run ends (None: until Ctrl-C)",
    )
    scan_every: int = Field(1, ge=1, description="log every n-th scan")
    mesh_every_submaps: int = Field(
        1, ge=1, description="extract and log the mesh every n-th closed submap"
    )
    mesh_after_remap: bool = Field(
        True, description="extract and log the mesh after every remapping pass"
    )
    mesh_time_share: float = Field(
        0.05,
        gt=0,
        le=1,
        description="the map worker extracts a mesh for the recording (mesh_every_submaps, "
        "mesh_after_remap) only when the meshes so far plus the next one (predicted from the "
        "map's size and the last mesh's time) take at most this share of the run's time, so "
        "that meshing a growing map does not slow the run; 1 extracts every mesh asked for; "
        "the final mesh is always logged",
    )
    flush_timeout_s: float = Field(
        10.0,
        gt=0,
        description="seconds the end of a run waits for Rerun to write or send what it still "
        "holds; a sink that cannot take it (a full disk, a closed viewer) would otherwise keep "
        "the run from ending: the recording then misses its end, with a warning",
    )


class OutputConfig(Strict):
    """The run folder."""

    root: Path = Field(Path("outputs"), description="parent folder of run folders")
    run_name: str | None = Field(
        None, description="run folder name (default: <dataset>-<sequence>-<time>)"
    )
    write_mesh: bool = Field(True, description="write mesh.ply at the end")
    write_map: bool = Field(True, description="write the neural map file at the end")
    mesh_samples: int = Field(
        100_000,
        ge=0,
        le=10_000_000,
        description="surface samples per mesh for mesh accuracy/completion; 0: the run does not "
        "score its mesh (python -m slam.eval scores it later, with 100,000); at most 10,000,000",
    )

    @field_validator("mesh_samples")
    @classmethod
    def _samples(cls, value: int) -> int:
        if 0 < value < 1000:
            raise ValueError("mesh_samples: 0 (no scoring) or at least 1000")
        return value


class RunConfig(Strict):
    """Everything a run needs."""

    source: SourceConfig = Field(default_factory=SourceConfig, description="input sequence")
    generated: GeneratedConfig = Field(
        default_factory=GeneratedConfig, description="generated sequence (dataset 'generated')"
    )
    odometry: OdometryConfig = Field(default_factory=OdometryConfig, description="odometry")
    submaps: SubmapConfig = Field(default_factory=SubmapConfig, description="keyframing")
    loop_closure: LoopClosureConfig = Field(
        default_factory=LoopClosureConfig, description="loop closure"
    )
    pose_graph: PoseGraphConfig = Field(default_factory=PoseGraphConfig, description="pose graph")
    remap: RemapConfig = Field(default_factory=RemapConfig, description="remapping")
    relocalise: LocaliseConfig = Field(
        default_factory=LocaliseConfig, description="localisation in a stored map (--map)"
    )
    mapping: MapConfig = Field(default_factory=MapConfig, description="the neural implicit map")
    viz: VizConfig = Field(default_factory=VizConfig, description="Rerun logging")
    output: OutputConfig = Field(default_factory=OutputConfig, description="run folder")
    threads: int = Field(
        0,
        ge=0,
        le=1024,
        description="CPU thread budget of the run (0 = the machine's cores, at most a "
        "container's CPU limit): KISS-ICP and OpenCV get all of it, torch all but one when "
        "map_worker is on, numpy/scipy BLAS one (slam/assembly/threads.py; idle pool threads "
        "spin, so oversubscribed pools thrash); at most 1024",
    )
    map_worker: bool = Field(
        True,
        description="run keyframing, normals, loop detection and the pose graph on one worker "
        "thread and encoding, fusion, remapping and map logging on another while the main "
        "thread runs the odometry; results do not depend on it (each worker applies its jobs in "
        "submission order)",
    )

    def pipeline_config(self) -> PipelineConfig:
        """The algorithm's part of this configuration (the same section objects, not copies)."""
        return PipelineConfig(**{name: getattr(self, name) for name in PipelineConfig.model_fields})


class UsageError(ValueError):
    """Bad command-line input (exit status 2)."""


class OneLineParser(argparse.ArgumentParser):
    """argparse whose errors are a :class:`UsageError` of one line (no usage block) that points
    to the command's ``--help``."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{message} (see {self.prog} --help)")


def set_nested(target: dict[str, Any], dotted: str, value: Any) -> None:
    """Set ``target[a][b][c] = value`` for ``dotted = "a.b.c"``, creating sections."""
    keys = dotted.split(".")
    node = target
    for key in keys[:-1]:
        node = node.setdefault(key, {})
        if not isinstance(node, dict):
            raise UsageError(f"--set {dotted}: '{key}' is not a config section")
    node[keys[-1]] = value


def set_overrides(items: list[str]) -> dict[str, Any]:
    """``--set KEY=VALUE`` arguments as a nested mapping (values parsed as YAML scalars)."""
    import yaml

    overrides: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--set '{item}': expected KEY=VALUE, e.g. submaps.max_frames=20")
        if _RANGE.fullmatch(raw):  # YAML 1.1 would read "10:5" as the base-60 number 605
            value: Any = raw.strip()
        else:
            try:
                value = yaml.safe_load(raw) if raw.strip() else None
            except yaml.YAMLError:
                value = raw
        set_nested(overrides, key.strip(), value)
    return overrides


_RANGE = re.compile(r"\s*[-+\d\s]*:[-+\d\s:]*")
"""A frame range ``A:B[:STEP]`` (parts may be empty), kept as text by :func:`set_overrides`."""


def set_origins(items: list[str]) -> dict[str, str]:
    """Dotted key of each ``--set`` argument -> the argument, to name it in errors."""
    origins = {}
    for item in items:
        key, _, _ = item.partition("=")
        origins[key.strip()] = f"--set {item}"
    return origins


def _location(loc: tuple[Any, ...]) -> str:
    return ".".join(str(part) for part in loc) or "<root>"


def _sibling_keys(model: type[BaseModel], loc: tuple[Any, ...]) -> list[str]:
    """The keys the model accepts beside the last part of ``loc`` ([] where it cannot tell)."""
    for part in loc[:-1]:
        field = model.model_fields.get(part) if isinstance(part, str) else None
        annotation = field.annotation if field is not None else None
        if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
            return []
        model = annotation
    return list(model.model_fields)


def _unknown_key_hint(model: type[BaseModel] | None, loc: tuple[Any, ...]) -> str:
    keys = _sibling_keys(model, loc) if model is not None and loc else []
    if not keys:
        return "check its spelling and section"
    close = difflib.get_close_matches(str(loc[-1]), keys, n=1)
    return f"did you mean '{close[0]}'?" if close else "valid keys here: " + ", ".join(keys)


def describe_validation_error(
    error: ValidationError, origin: str, model: type[BaseModel] | None = RunConfig
) -> str:
    """One line naming the first offending key of a pydantic error; for an unknown key, the
    closest valid one of ``model`` (the validated model) or the valid keys at that level."""
    first = error.errors()[0]
    key = _location(first["loc"])
    if first["type"] == "extra_forbidden":
        return f"{origin}: unknown key '{key}'; {_unknown_key_hint(model, tuple(first['loc']))}"
    if first["type"] == "missing":
        return f"{origin}: missing key '{key}'"
    shown = repr(first.get("input"))
    if len(shown) > 60:
        shown = shown[:57] + "..."
    return f"{origin}: invalid value {shown} for '{key}': {first['msg']}"


def merge_overrides(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``base`` with the nested mapping ``override`` applied on top (neither is modified)."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_overrides(out[key], value)
        else:
            out[key] = value
    return out


def read_yaml(path: Path) -> dict[str, Any]:
    """A YAML mapping from a file (empty file: empty mapping)."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found; pass an existing YAML file")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{path}:{where} is not valid YAML; fix the syntax") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping of config sections")
    return data


def build_run_config(
    data: dict[str, Any], origin: str, override_origins: dict[str, str] | None = None
) -> RunConfig:
    """Validate a nested mapping into a :class:`RunConfig` (one-line :class:`ConfigError`).

    ``override_origins`` maps dotted keys to where they were set (``--set KEY=VALUE``): an error
    at, below or above such a key (an unknown section it created) names that argument instead
    of ``origin``.
    """
    try:
        return RunConfig.model_validate(data)
    except ValidationError as exc:
        key = _location(exc.errors()[0]["loc"])
        for dotted, argument in (override_origins or {}).items():
            if key == dotted or key.startswith(dotted + ".") or dotted.startswith(key + "."):
                origin = argument
                break
        raise ConfigError(describe_validation_error(exc, origin)) from None


def load_run_config(
    path: Path | None = None,
    overrides: dict[str, Any] | None = None,
    override_origins: dict[str, str] | None = None,
) -> RunConfig:
    """Read ``path`` (YAML), apply nested ``overrides`` on top, validate.

    Raises:
        ConfigError: one line naming the file (or the ``--set`` argument, see
            :func:`build_run_config`) and the offending key.
    """
    data = read_yaml(path) if path is not None else {}
    origin = str(path) if path is not None else "config"
    if overrides:
        data = merge_overrides(data, overrides)
    return build_run_config(data, origin, override_origins)


def default_config_path(name: str) -> Path:
    """``configs/<name>.yaml`` of the repository."""
    return CONFIG_DIR / f"{name}.yaml"


def dump_run_config(cfg: RunConfig) -> str:
    """The resolved config as YAML text (paths as strings)."""
    import yaml

    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)
