"""Key expressions. Everything a rig says lives under ``hil/<rig>/``.

Data under ``hil/<rig>/<robot>/...``, rig-wide control (e-stop, plan, model updates,
reset) beside it, and presence (liveliness tokens) under ``hil/<rig>/alive/<node>``.
"""

from __future__ import annotations

import re

_NAME = re.compile(r"^[A-Za-z0-9_\-]+$")


def _check(*parts: str) -> None:
    for p in parts:
        if not _NAME.match(p):
            raise ValueError(f"bad key segment {p!r}: use letters, digits, '_' and '-'")


def root(rig: str) -> str:
    _check(rig)
    return f"hil/{rig}"


def all_of(rig: str) -> str:
    return f"{root(rig)}/**"


def state(rig: str, robot: str) -> str:
    _check(robot)
    return f"{root(rig)}/{robot}/state"


def cmd(rig: str, robot: str) -> str:
    _check(robot)
    return f"{root(rig)}/{robot}/cmd"


def spec(rig: str, robot: str) -> str:
    _check(robot)
    return f"{root(rig)}/{robot}/spec"


def image(rig: str, camera: str) -> str:
    _check(camera)
    return f"{root(rig)}/{camera}/image"


def estop(rig: str) -> str:
    return f"{root(rig)}/estop"


def plan(rig: str) -> str:
    return f"{root(rig)}/mpc/plan"


def model_update(rig: str) -> str:
    return f"{root(rig)}/model/update"


def reset(rig: str, what: str) -> str:
    _check(what)
    return f"{root(rig)}/reset/{what}"


def alive(rig: str, node: str) -> str:
    _check(node)
    return f"{root(rig)}/alive/{node}"


def alive_all(rig: str) -> str:
    return f"{root(rig)}/alive/*"
