"""Key expressions. Everything a rig says lives under ``hil/<rig>/``.

Data under ``hil/<rig>/<robot>/...``, rig-wide control (e-stop, plan, model updates,
reset) beside it, and presence (liveliness tokens) under ``hil/<rig>/alive/<node>``.
The e-stop has four keys: engage commands on ``hil/<rig>/estop``, releases on
``hil/<rig>/estop/release/<user>`` (the key names who released), driver acknowledgements
on ``hil/<rig>/estop/ack`` and every node's latched state as a queryable under
``hil/<rig>/estop/latch/<node>``.
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
    """E-stop commands (``EStop``: engage or release), from ``hil estop`` or any node."""
    return f"{root(rig)}/estop"


def estop_release(rig: str, user: str) -> str:
    """Releases of the e-stop by ``user`` (``EStop`` with ``engaged=False``). A release on
    :func:`estop` is refused: the key names who released, and on a rig with access control
    Zenoh's ACL lets only ``user``'s credentials publish on it (bus/access.py)."""
    _check(user)
    return f"{root(rig)}/estop/release/{user}"


def estop_release_all(rig: str) -> str:
    return f"{root(rig)}/estop/release/*"


def estop_ack(rig: str) -> str:
    """Driver nodes' acknowledgements of e-stop commands (``EStopAck``)."""
    return f"{root(rig)}/estop/ack"


def estop_latch(rig: str, node: str) -> str:
    """Queryable of one node's latched e-stop (the last ``EStop`` it heard)."""
    _check(node)
    return f"{root(rig)}/estop/latch/{node}"


def estop_latch_all(rig: str) -> str:
    return f"{root(rig)}/estop/latch/*"


def plan(rig: str) -> str:
    return f"{root(rig)}/mpc/plan"


def model_update(rig: str) -> str:
    """Adapted dynamics models from the adaptation node to the MPC (``ModelUpdate``)."""
    return f"{root(rig)}/model/update"


def task_posterior(rig: str) -> str:
    """MOLe's posterior over its tasks after each EM step (``TaskPosterior``)."""
    return f"{root(rig)}/model/posterior"


def reset(rig: str, what: str) -> str:
    _check(what)
    return f"{root(rig)}/reset/{what}"


def reset_all(rig: str) -> str:
    """Every reset message of the rig (requests, answers, supervisor transitions)."""
    return f"{root(rig)}/reset/**"


def reset_transition(rig: str) -> str:
    """The reset supervisor's state-machine transitions (``ResetTransition``)."""
    return reset(rig, "transition")


def reset_driver(rig: str) -> str:
    """Reset supervisor → driver node (``ResetEvent`` phase ``teleport`` or ``episode``)."""
    return reset(rig, "driver")


def reset_driver_done(rig: str) -> str:
    """Driver node → reset supervisor: the answer to a ``reset_driver`` request."""
    return reset(rig, "driver_done")


#: the reset supervisor's node name; a driver node leaves controller reset requests to it while it is alive
RESET_SUPERVISOR_NODE = "reset-supervisor"

#: driver bridge nodes are named ``driver-<robot>``; e-stop acks and replay refusal look for them
DRIVER_NODE_PREFIX = "driver-"


def driver_node(robot: str) -> str:
    _check(robot)
    return f"{DRIVER_NODE_PREFIX}{robot}"


def alive(rig: str, node: str) -> str:
    _check(node)
    return f"{root(rig)}/alive/{node}"


def alive_all(rig: str) -> str:
    return f"{root(rig)}/alive/*"
