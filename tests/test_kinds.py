"""One description of a dataset kind: ``datasets/kinds.py``. A mixture's sources are told apart and read back by the
same ``config_kind`` / ``config_from`` that export, statistics and previews use, restricted to ``SOURCE_KINDS``;
``datasets/mixture.py`` keeps no kind table of its own."""

from __future__ import annotations

import pytest

from flowsynth.datasets import BouncingThings, Layers, LayersConfig, Mixture, MixtureConfig, kinds, make_stream, mixture
from flowsynth.errors import ConfigError
from flowsynth.scene import BouncingThingsConfig

THINGS = BouncingThingsConfig(width=32, height=32, num_frames=2)
CHAIRS = LayersConfig(width=32, height=32, num_frames=2)


def test_every_kind_is_described_once_and_round_trips():
    mix = MixtureConfig({"things": THINGS, "chairs": CHAIRS})
    for cfg, kind, stream in ((THINGS, "bouncing", BouncingThings), (CHAIRS, "layers", Layers),
                              (mix, "mixture", Mixture)):
        assert kinds.config_kind(cfg) == kind and kind in kinds.KINDS
        assert kinds.config_from(kind, cfg.to_dict()) == cfg
        assert type(make_stream(cfg, ["rgb", "flow_fw"])) is stream
    assert kinds.SOURCE_KINDS == ("bouncing", "layers")


def test_mixture_keeps_no_kind_table_of_its_own():
    for name in ("source_kind", "source_config", "SOURCE_KINDS"):
        assert not hasattr(mixture, name) or getattr(mixture, name) is getattr(kinds, name, None), name


def test_a_source_is_one_of_the_source_kinds():
    mix = MixtureConfig({"things": THINGS, "chairs": CHAIRS})
    assert kinds.config_kind(CHAIRS, kinds.SOURCE_KINDS) == "layers"
    with pytest.raises(ConfigError, match="a source config must be a BouncingThingsConfig or a LayersConfig, got "
                                          "MixtureConfig"):
        kinds.config_kind(mix, kinds.SOURCE_KINDS)
    with pytest.raises(ConfigError, match=r"unknown source kind 'mixture'; kinds: \['bouncing', 'layers'\]"):
        kinds.config_from("mixture", mix.to_dict(), kinds.SOURCE_KINDS)
    with pytest.raises(ConfigError, match="a dataset config must be a BouncingThingsConfig, a LayersConfig or a "
                                          "MixtureConfig, got dict"):
        kinds.config_kind({})
    with pytest.raises(ConfigError, match=r"unknown dataset kind 'chairs'"):
        kinds.config_from("chairs", {})
    preset = mix.to_dict()
    preset["sources"][1]["kind"] = "mixture"  # a mixture inside a mixture: refused by the same rule
    with pytest.raises(ConfigError, match="source 'chairs': unknown source kind 'mixture'"):
        MixtureConfig.from_dict(preset)
    with pytest.raises(ConfigError, match="config 'm' must be a BouncingThingsConfig, a LayersConfig"):
        MixtureConfig({"m": mix})
