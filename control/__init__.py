"""hilstack control: planners, costs, paths, baselines.

Public names are imported lazily so that ``import control`` (e.g. for a safety node) does not
pull in torch::

    from control import PDDM, CEM, RandomShooting, PathCost, make_path, DifferentialDriveController
"""

from importlib import import_module

_EXPORTS = {
    "Planner": "control.planners",
    "RandomShooting": "control.planners",
    "CEM": "control.planners",
    "PDDM": "control.planners",
    "PathCost": "control.costs",
    "evaluate_path_following": "control.costs",
    "summarize_paths": "control.costs",
    "rank_key": "control.costs",
    "make_path": "control.paths",
    "fillet": "control.paths",
    "PATHS": "control.paths",
    "DifferentialDriveController": "control.baselines",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'control' has no attribute {name!r}")
