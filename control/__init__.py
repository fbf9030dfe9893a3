"""hilstack control: planners, costs, paths, baselines.

Public names are imported lazily so that ``import control`` (e.g. for a safety node) does not
pull in torch::

    from hilstack.control import PDDM, CEM, RandomShooting, PathCost, make_path, DifferentialDriveController
"""

from importlib import import_module

_EXPORTS = {
    "Planner": "hilstack.control.planners",
    "RandomShooting": "hilstack.control.planners",
    "CEM": "hilstack.control.planners",
    "PDDM": "hilstack.control.planners",
    "PathCost": "hilstack.control.costs",
    "evaluate_path_following": "hilstack.control.costs",
    "summarize_paths": "hilstack.control.costs",
    "rank_key": "hilstack.control.costs",
    "make_path": "hilstack.control.paths",
    "fillet": "hilstack.control.paths",
    "PATHS": "hilstack.control.paths",
    "DifferentialDriveController": "hilstack.control.baselines",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'control' has no attribute {name!r}")
