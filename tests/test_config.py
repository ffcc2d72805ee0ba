"""Run configuration: every shipped YAML loads, unknown keys and bad values fail in one line."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from slam.assembly.config import (
    CONFIG_DIR,
    ConfigError,
    RunConfig,
    build_run_config,
    dump_run_config,
    load_run_config,
    set_origins,
)

# YAML files in configs/ that configure something other than a run.
NOT_RUN_CONFIGS = {"train_prior.yaml"}
RUN_CONFIGS = sorted(p for p in CONFIG_DIR.glob("*.yaml") if p.name not in NOT_RUN_CONFIGS)


def test_the_dataset_configs_exist():
    names = {p.stem for p in RUN_CONFIGS}
    assert {"kitti", "icl", "tum", "replica", "7scenes", "demo", "generated-lidar"} <= names


@pytest.mark.parametrize("path", RUN_CONFIGS, ids=lambda p: p.name)
def test_every_run_config_loads(path: Path):
    cfg = load_run_config(path)
    assert isinstance(cfg, RunConfig)
    assert cfg.submaps.map_voxel_m < cfg.mapping.voxel_size_m
    again = build_run_config(yaml.safe_load(dump_run_config(cfg)), "dumped")
    assert again == cfg


def test_unknown_key_names_the_key(tmp_path: Path):
    path = tmp_path / "bad.yaml"
    path.write_text("loop_closure:\n  lidar:\n    top_kk: 3\n")
    with pytest.raises(ConfigError) as info:
        load_run_config(path)
    message = str(info.value)
    assert "loop_closure.lidar.top_kk" in message
    assert str(path) in message
    assert "\n" not in message


def test_unknown_key_suggests_the_closest_or_lists_the_valid_ones():
    with pytest.raises(ConfigError, match=r"did you mean 'top_k'\?$"):
        build_run_config({"loop_closure": {"lidar": {"top_kk": 3}}}, "x.yaml")
    with pytest.raises(ConfigError, match=r"did you mean 'mapping'\?$"):
        build_run_config({"mapings": {}}, "x.yaml")
    with pytest.raises(ConfigError) as info:
        build_run_config({"remap": {"zzz": 1}}, "x.yaml")
    listed = str(info.value).rsplit("valid keys here: ", 1)[1].split(", ")
    assert set(listed) == set(RunConfig.model_fields["remap"].annotation.model_fields)


def test_unknown_section_from_set_names_the_argument():
    origins = set_origins(["mapings.voxel_size_m=1"])
    with pytest.raises(ConfigError, match=r"^--set mapings\.voxel_size_m=1: unknown key"):
        build_run_config({"mapings": {"voxel_size_m": 1}}, "x.yaml", origins)


def test_unknown_section_and_bad_value(tmp_path: Path):
    with pytest.raises(ConfigError, match="unknown key 'mapings'"):
        build_run_config({"mapings": {}}, "x.yaml")
    with pytest.raises(ConfigError, match=r"submaps\.max_frames") as info:
        build_run_config({"submaps": {"max_frames": 0}}, "x.yaml")
    assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match=r"mapping\.voxel_size_m"):
        build_run_config({"mapping": {"voxel_size_m": "big"}}, "x.yaml")
    # mesh scoring: off (0) or at least 1000 samples, nothing between
    assert build_run_config({"output": {"mesh_samples": 0}}, "x.yaml").output.mesh_samples == 0
    with pytest.raises(ConfigError, match=r"output\.mesh_samples.*at least 1000") as info:
        build_run_config({"output": {"mesh_samples": 500}}, "x.yaml")
    assert "\n" not in str(info.value)


def test_bad_yaml_and_missing_file(tmp_path: Path):
    broken = tmp_path / "broken.yaml"
    broken.write_text("submaps: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_run_config(broken)
    with pytest.raises(ConfigError, match="not found"):
        load_run_config(tmp_path / "missing.yaml")
    listing = tmp_path / "list.yaml"
    listing.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_run_config(listing)


def test_overrides_apply_on_top_of_the_file():
    cfg = load_run_config(
        CONFIG_DIR / "demo.yaml", {"submaps": {"max_frames": 7}, "mapping": {"device": "cpu"}}
    )
    assert cfg.submaps.max_frames == 7
    assert cfg.mapping.device == "cpu"
    assert cfg.generated.kind == "rgbd"  # untouched keys keep the file's values


def test_every_field_is_documented():
    def walk(model):
        for name, field in model.model_fields.items():
            assert field.description, f"{model.__name__}.{name} has no description"
            annotation = field.annotation
            if isinstance(annotation, type) and issubclass(annotation, RunConfig.__base__):
                walk(annotation)

    walk(RunConfig)
