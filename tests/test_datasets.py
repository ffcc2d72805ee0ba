"""The dataset registry agrees with itself: every command-line name reaches a source, a default
config and keyword arguments that the source's constructor takes."""

from __future__ import annotations

import inspect

import pytest

from frontends.sources import SOURCES, make_source
from slam.assembly.config import ConfigError, default_config_path, load_run_config
from slam.assembly.datasets import DATASETS, SOURCE_OPTIONS, source_kwargs


def test_every_source_has_options_and_every_option_a_source():
    assert set(SOURCE_OPTIONS) == set(SOURCES)
    assert {entry.source for entry in DATASETS.values()} <= set(SOURCES)


@pytest.mark.parametrize("name", sorted(DATASETS))
def test_each_dataset_name_gives_arguments_its_source_accepts(name: str):
    entry = DATASETS[name]
    cfg = load_run_config(
        default_config_path(entry.config),
        {"source": {"root": "/nonexistent", "sequence": "00", "frames": "0:2"}},
    )
    assert cfg.source.dataset == entry.source
    kwargs = source_kwargs(cfg)
    signature = inspect.signature(SOURCES[entry.source].__init__)
    signature.bind(None, **kwargs)  # raises TypeError on an argument the source does not take
    assert kwargs["frames"] == slice(0, 2)


def test_an_unknown_source_is_one_line_naming_the_choices():
    with pytest.raises(ConfigError, match=r"unknown source 'kitty'.*kitti"):
        load_run_config(default_config_path("kitti"), {"source": {"dataset": "kitty"}})
    with pytest.raises(Exception, match=r"unknown source 'kitty'"):
        make_source("kitty", root=".")
