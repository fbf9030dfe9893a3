"""hilstack learning: datasets, dynamics models, training.

Public names are imported lazily so that ``import learning`` stays cheap (no torch import)::

    from hilstack.learning import EnsembleDynamics, Episode, TransitionDataset, load_episodes
"""

from importlib import import_module

_EXPORTS = {
    "Episode": "hilstack.learning.datasets",
    "NormStats": "hilstack.learning.datasets",
    "TransitionDataset": "hilstack.learning.datasets",
    "episodes_from_table": "hilstack.learning.datasets",
    "load_episodes": "hilstack.learning.datasets",
    "EnsembleDynamics": "hilstack.learning.dynamics",
    "cpu_bf16_support": "hilstack.learning.dynamics",
    "h_step_error": "hilstack.learning.dynamics",
    "h_step_windows": "hilstack.learning.dynamics",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'learning' has no attribute {name!r}")
