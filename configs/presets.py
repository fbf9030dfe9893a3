"""Named presets of a config dataclass: the one way every demo and experiment config offers them.

A config class mixes in :class:`Presets` and lists its presets as field overrides of its
defaults in ``PRESETS`` (a ``ClassVar``); callers build one with ``Cfg.from_preset("quick", seed=1)``
(keyword arguments override the preset) and list them with ``Cfg.preset_names()``::

    @dataclass
    class DemoConfig(Presets):
        PRESETS: ClassVar[dict[str, dict]] = {"quick": {"rollouts": 10}, "full": {"rollouts": 400}}
        rollouts: int = 100

    DemoConfig.from_preset("quick", rollouts=12)
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar, TypeVar

__all__ = ["Presets"]

C = TypeVar("C", bound="Presets")


class Presets:
    """Mixin: ``from_preset(name, **overrides)`` and ``preset_names()`` from the class's ``PRESETS``."""

    #: preset name -> field values that differ from the dataclass defaults
    PRESETS: ClassVar[Mapping[str, Mapping[str, Any]]] = {}

    @classmethod
    def from_preset(cls: type[C], name: str, **overrides: Any) -> C:
        """The preset ``name`` with ``overrides`` on top (one-line ValueError for an unknown name)."""
        if name not in cls.PRESETS:
            known = ", ".join(cls.PRESETS) or "none"
            raise ValueError(f"{cls.__name__}: unknown preset {name!r}; presets: {known}")
        return cls(**{**cls.PRESETS[name], **overrides})

    @classmethod
    def preset_names(cls) -> tuple[str, ...]:
        return tuple(cls.PRESETS)
