"""Who may command and who may release a rig: Zenoh user/password authentication and ACL.

A rig whose ``bus:`` section has ``access:`` (:class:`hilstack.configs.schema.BusAccess`)
runs as a star: its driver node opens the rig's endpoint as a Zenoh **router** that
authenticates every session against the credentials file (Zenoh's ``usrpwd``
dictionary: one ``user:password`` line each) and filters what they may publish with
Zenoh's access control (``access_control``, default ``deny``); every other node of the
rig is a Zenoh **client** of that router, with the user and password of its line. A
session without valid credentials cannot connect at all. Of the authenticated ones:

- every user may listen (subscribe, query, liveliness) and engage the e-stop
  (``hil/<rig>/estop``);
- ``command`` users may publish the robots' commands (``hil/<rig>/<robot>/cmd``), reset
  requests, plans and model updates;
- a ``release`` user U may publish a release only on ``hil/<rig>/estop/release/U``: the
  key names the sender and the ACL binds it to U's credentials, so a release always
  says who sent it.

Rules name concrete keys or patterns that contain no command key: Zenoh's ACL does not
match a message whose key is wider than a rule's (a put on ``hil/<rig>/**`` is not
"inside" ``hil/<rig>/*/cmd``), so with a default ``allow`` and deny rules a wildcard put
would pass and reach the driver's command subscriber; with default ``deny`` it is
simply dropped.
"""

from __future__ import annotations

import getpass
import os
import secrets
import stat
from pathlib import Path
from typing import Any

from hilstack.bus import keys
from hilstack.configs.schema import BusAccess, BusConfig

#: environment overrides of ``bus.access.credentials`` and ``bus.access.user``
CREDENTIALS_ENV = "HIL_CREDENTIALS"
USER_ENV = "HIL_BUS_USER"

#: key segments under ``hil/<rig>/`` that are rig-wide (a robot may not be named so on an access rig:
#: its ``cmd`` key would fall inside a pattern every user may publish on, or the reverse)
RESERVED = ("estop", "mpc", "model", "reset", "alive", "foxglove")

#: what listening needs (every authenticated user, both directions)
_OBSERVE = [
    "declare_subscriber", "declare_queryable", "query", "reply",
    "liveliness_token", "liveliness_query", "declare_liveliness_subscriber",
]


class AccessError(ValueError):
    """Access control cannot be set up as configured (one line: what and where)."""


def credentials_path(access: BusAccess) -> Path:
    raw = os.environ.get(CREDENTIALS_ENV) or access.credentials
    return Path(os.path.expandvars(os.path.expanduser(raw)))


def user_of(access: BusAccess) -> str:
    return os.environ.get(USER_ENV) or access.user


def identity(bus: BusConfig | None) -> str:
    """Who this process is on the bus: its credentials' user on an access rig, else the OS user."""
    if bus is not None and bus.access is not None:
        return user_of(bus.access)
    try:
        name = getpass.getuser()
    except Exception:  # no user database entry (containers)
        name = f"uid{os.getuid()}"
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in name) or "unknown"


def read_credentials(path: Path) -> dict[str, str]:
    """user → password. Refuses a missing file, one readable by group or others, bad lines."""
    if not path.is_file():
        raise AccessError(f"credentials file {path} not found: create it with `hil credentials RIG` "
                          f"(or point {CREDENTIALS_ENV} at yours)")
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o077:
        raise AccessError(f"credentials file {path} is readable by others (mode {mode:o}): chmod 600 {path}")
    out: dict[str, str] = {}
    for i, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        user, sep, pw = line.partition(":")
        if not sep or not user or not pw:
            raise AccessError(f"credentials file {path}: line {i}: expected user:password")
        try:
            keys._check(user)
        except ValueError as e:
            raise AccessError(f"credentials file {path}: line {i}: {e}") from None
        out[user] = pw
    if not out:
        raise AccessError(f"credentials file {path} holds no user:password line")
    return out


def generate(path: Path, users: list[str]) -> list[str]:
    """Add a random password for each of ``users`` not in ``path`` yet (created 0600); returns those added."""
    path.parent.mkdir(parents=True, exist_ok=True)
    have = read_credentials(path) if path.exists() else {}
    added = [u for u in dict.fromkeys(users) if u not in have]
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    with os.fdopen(fd, "a") as f:
        for u in added:
            f.write(f"{u}:{secrets.token_urlsafe(24)}\n")
    os.chmod(path, 0o600)
    return added


def provision(rig: str, bus: BusConfig, backends: list[str]) -> str | None:
    """Create the credentials file of a rig without real hardware when it is missing, so an
    emulated rig runs unattended (CI, a fresh clone): a random password for ``bus.access.user``
    and every command and release user, mode 600, where the rig (or HIL_CREDENTIALS) says.
    Returns the one line to tell the user, or None (no access control, the file exists, or a
    real robot: its file is made on purpose with `hil credentials RIG`, and its absence stays
    the one-line error of :func:`read_credentials`)."""
    acc = bus.access
    if acc is None or "real" in backends:
        return None
    path = credentials_path(acc)
    if path.exists():
        return None
    added = generate(path, [acc.user, *acc.command, *acc.release, *(acc.drive if bus.router else [])])
    return f"created credentials for rig {rig} in {path} (users {', '.join(added)}; mode 600)"


def acl(rig: str, robots: list[str], access: BusAccess, drivers: bool = False) -> dict[str, Any]:
    """The Zenoh ``access_control`` section of the rig's router (see the module docstring).
    ``drivers`` (a separate router, ``hil router``): the driver nodes are its clients too, and
    ``access.drive`` users may publish anything under the rig's root (states, specs, e-stop acks)."""
    bad = sorted(set(robots) & set(RESERVED))
    if bad:
        raise AccessError(f"rig {rig}: robot name(s) {bad} are reserved on a rig with access control ({RESERVED})")
    root = keys.root(rig)
    rules: list[dict[str, Any]] = [
        {"id": "observe", "permission": "allow", "messages": _OBSERVE, "key_exprs": [f"{root}/**"]},
        {"id": "deliver", "permission": "allow", "flows": ["egress"], "messages": ["put", "delete"],
         "key_exprs": [f"{root}/**"]},
        {"id": "engage", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
         "key_exprs": [keys.estop(rig)]},
        {"id": "command", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
         "key_exprs": [keys.cmd(rig, r) for r in robots] + [keys.reset_all(rig), f"{root}/mpc/**", f"{root}/model/**"]},
    ]
    subjects: list[dict[str, Any]] = [{"id": "any"}]
    policies: list[dict[str, Any]] = [{"id": "everyone", "rules": ["observe", "deliver", "engage"], "subjects": ["any"]}]
    if access.command:
        subjects.append({"id": "commanders", "usernames": list(access.command)})
        policies.append({"id": "commanders", "rules": ["command"], "subjects": ["commanders"]})
    if drivers:
        rules.append({"id": "drive", "permission": "allow", "flows": ["ingress"], "messages": ["put", "delete"],
                      "key_exprs": [f"{root}/**"]})
        subjects.append({"id": "drivers", "usernames": list(access.drive)})
        policies.append({"id": "drivers", "rules": ["drive"], "subjects": ["drivers"]})
    for u in access.release:
        rules.append({"id": f"release-{u}", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
                      "key_exprs": [keys.estop_release(rig, u)]})
        subjects.append({"id": f"user-{u}", "usernames": [u]})
        policies.append({"id": f"release-{u}", "rules": [f"release-{u}"], "subjects": [f"user-{u}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
