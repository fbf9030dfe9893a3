"""The automated-reset supervisor: episode-end detection, reset procedures, verification.

- :mod:`hilstack.control.reset.config`: the ``reset:`` section of a rig config (data).
- :mod:`hilstack.control.reset.detectors`: pluggable episode-end detectors (timeout, arena, drop).
- :mod:`hilstack.control.reset.steps`: reset steps (drive to start, teleport, task-reset mechanism).
- :mod:`hilstack.control.reset.supervisor`: the node and its state machine (docs/reset.md).
"""

from hilstack.control.reset.config import ResetConfig, load_reset

__all__ = ["ResetConfig", "load_reset"]
