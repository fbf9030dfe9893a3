"""Named presets (configs/presets.py): one way for every demo and experiment config."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import pytest

from hilstack.configs.presets import Presets


@dataclass
class _Cfg(Presets):
    PRESETS: ClassVar[dict] = {"quick": {"n": 2}, "full": {"n": 9, "tag": "f"}}
    n: int = 1
    tag: str = ""


def test_preset_overrides_the_defaults_and_keywords_override_the_preset():
    assert _Cfg.from_preset("quick") == _Cfg(n=2)
    assert _Cfg.from_preset("full", tag="x") == _Cfg(n=9, tag="x")
    assert _Cfg.preset_names() == ("quick", "full")
    assert _Cfg.PRESETS["quick"] == {"n": 2}  # building one does not change the table


def test_unknown_preset_is_a_one_line_error_naming_the_presets():
    with pytest.raises(ValueError, match=r"^_Cfg: unknown preset 'fast'; presets: quick, full$"):
        _Cfg.from_preset("fast")


def test_every_config_builds_each_of_its_presets():
    from hilstack.learning.adaptation.experiment import AdaptationConfig
    from hilstack.learning.adaptation.gym_suite import GymSuiteConfig
    from hilstack.learning.baoding import BaodingConfig
    from hilstack.learning.mbrl import MbrlConfig
    from hilstack.learning.reach import ReachConfig
    from hilstack.tools.demo_transfer import TransferDemoConfig

    for cls in (AdaptationConfig, GymSuiteConfig, BaodingConfig, MbrlConfig, ReachConfig, TransferDemoConfig):
        assert len(cls.preset_names()) >= 2, cls
        for name in cls.preset_names():
            cfg = cls.from_preset(name)  # each runs its own validation
            for k, v in cls.PRESETS[name].items():
                assert getattr(cfg, k) == v, (cls.__name__, name, k)
    assert AdaptationConfig.from_preset("quick", seeds=(4,)).seeds == (4,)
    assert TransferDemoConfig.from_preset("full").pendulum.target_sizes == (500, 3000)
