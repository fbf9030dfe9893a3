"""Effects a device model can add to the sim's MuJoCo model (the emulators' ``effects`` option).

Shared by the servo (dynamixel) and hand firmware models: calibration's tests inject one and check
that it is named. Each firmware keeps its own table of keys -> (config field, upper bound).
"""

from __future__ import annotations

import math

#: the Coulomb friction's sign function is linear below this speed (a smooth stick, stable at 1 kHz)
FRICTION_V_EPS_RAD_S = 0.02


def validate_effects(effects: dict | None, table: dict[str, tuple[str, float]]) -> dict[str, float]:
    """``effects`` (key -> value) as config fields per ``table`` (key -> (field, upper bound)).

    Raises ValueError naming the bad key or value (unknown, not finite, out of [0, bound])."""
    out = {}
    for key, value in (effects or {}).items():
        if key not in table:
            raise ValueError(f"effects: unknown effect {key!r}; known: {sorted(table)}")
        field, bound = table[key]
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"effects.{key}: not a number: {value!r}") from None
        if not (math.isfinite(v) and 0.0 <= v <= bound):
            raise ValueError(f"effects.{key}: {value!r} is outside [0, {bound:g}]")
        out[field] = v
    return out
