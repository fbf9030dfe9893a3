"""hilstack learning: datasets, dynamics models, training.

Public names are imported lazily so that ``import learning`` stays cheap (no torch import)::

    from learning import EnsembleDynamics, Episode, TransitionDataset, load_episodes
"""

from importlib import import_module

_EXPORTS = {
    "Episode": "learning.datasets",
    "NormStats": "learning.datasets",
    "TransitionDataset": "learning.datasets",
    "episodes_from_table": "learning.datasets",
    "load_episodes": "learning.datasets",
    "EnsembleDynamics": "learning.dynamics",
    "cpu_bf16_support": "learning.dynamics",
    "h_step_error": "learning.dynamics",
    "h_step_windows": "learning.dynamics",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'learning' has no attribute {name!r}")
