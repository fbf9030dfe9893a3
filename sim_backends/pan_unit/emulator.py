"""The pan unit's device emulator: the Dynamixel bus emulator (sim_backends/dynamixel/emulator.py)
on the pan unit's world, in real time.

    python -m hilstack.sim_backends.pan_unit.emulator --print-pty --config '{"pan_id": 1}'
"""

from __future__ import annotations

import sys
from typing import Any

from hilstack.sim_backends.dynamixel.emulator import main as serve
from hilstack.sim_backends.pan_unit.world import PanWorld


def make_world(cfg: dict[str, Any]) -> PanWorld:
    return PanWorld(int(cfg.get("pan_id", 1)))


def main(argv: list[str] | None = None) -> int:
    return serve(argv, make_world, "python -m hilstack.sim_backends.pan_unit.emulator")


if __name__ == "__main__":
    sys.exit(main())
