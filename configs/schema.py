"""Typed config schemas (pydantic), validated at the edge with file+field errors."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, ClassVar, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

CONFIG_ROOT = Path(__file__).resolve().parent

M = TypeVar("M", bound=BaseModel)


class ConfigError(ValueError):
    """A config that cannot be used. ``str()`` names file, field and expectation."""

    def __init__(self, file: str | Path | None, problems: list[tuple[str, str]]):
        self.file = str(file) if file is not None else "<inline>"
        self.problems = problems
        lines = [f"{self.file}: {fld or '<root>'}: {msg}" for fld, msg in problems]
        super().__init__("invalid config\n  " + "\n  ".join(lines))


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


_NAME_RE = r"^[A-Za-z0-9_\-]+$"


class BusAccess(Strict):
    """Who may command and who may release the rig (bus/access.py, docs/platform.md "Who may
    command and who may release").

    The driver node owns the rig's endpoint as a Zenoh router that authenticates every
    session (user/password) against ``credentials`` and filters by Zenoh ACL: only
    ``command`` users may publish robot commands (and resets, plans, model updates), only
    ``release`` users may release the e-stop, every authenticated session may engage it
    and listen. A session without the rig's credentials cannot connect at all. The file
    holds ``user:password`` lines (Zenoh's usrpwd dictionary), is never in the repository
    and must be readable by its owner only; ``hil credentials RIG`` creates it, and ``hil up``
    (or a demo) does when it is missing on a rig without real robots."""

    #: the credentials file (``~`` and ``$VARS`` expanded); the environment variable
    #: HIL_CREDENTIALS overrides it
    credentials: str = Field(min_length=1)
    #: who this process is on the bus (its line of the credentials file); HIL_BUS_USER overrides it
    user: str = Field("operator", pattern=_NAME_RE)
    #: users that may command the robots
    command: list[str] = Field(default_factory=lambda: ["operator"])
    #: users that may release the e-stop (each release names its sender)
    release: list[str] = Field(default_factory=lambda: ["operator"])

    @field_validator("command", "release")
    @classmethod
    def _names(cls, v: list[str]) -> list[str]:
        for n in v:
            if not re.match(_NAME_RE, n):
                raise ValueError(f"user name {n!r}: use letters, digits, '_' and '-'")
        return v


class BusConfig(Strict):
    """Zenoh session. Default: peer-to-peer on loopback, no router, no multicast.

    Every node tries to listen on ``endpoint`` and also connects to it: the first node
    of a rig to start owns the port, the others connect to it and find each other by
    gossip over that link (gossip is not multicast: it only uses established links).
    A lab spreads nodes over hosts with ``mode: client`` and ``connect`` set to a
    Zenoh router (``tcp/10.0.0.2:7447``)."""

    mode: Literal["peer", "client"] = "peer"
    endpoint: str = "tcp/127.0.0.1:7447"
    listen: list[str] = Field(default_factory=list)
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False
    gossip: bool = True
    #: access control (authentication + ACL); required for rigs with real or emulated robots
    access: BusAccess | None = None

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        for e in v:
            _check_endpoint(e)
        return v

    @field_validator("endpoint")
    @classmethod
    def _endpoint(cls, v: str) -> str:
        return _check_endpoint(v)


def _check_endpoint(e: str) -> str:
    if not re.match(r"^(tcp|udp|tls|quic|unixsock-stream|ws)/.+", e):
        raise ValueError(f"endpoint {e!r} must look like 'tcp/127.0.0.1:7447'")
    return e


class RobotConfig(BaseModel):
    """One robot. ``params`` are validated by the robot's own settings class."""
    RECORDS_SOURCE: ClassVar[bool] = True  # parse_model fills ``source`` with the file path

    model_config = ConfigDict(extra="forbid", frozen=True)

    robot: str
    backend: Literal["real", "emulated", "sim"] = "sim"
    #: robot-specific parameters (sim model, port, limits...), checked by the robot package
    params: dict[str, Any] = Field(default_factory=dict)
    #: the file it came from, for error messages
    source: str | None = None


class RigRobot(Strict):
    config: str
    backend: Literal["real", "emulated", "sim"] | None = None
    params: dict[str, Any] = Field(default_factory=dict)


class RigConfig(Strict):
    RECORDS_SOURCE: ClassVar[bool] = True  # parse_model fills ``source`` with the file path
    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    robots: dict[str, RigRobot]
    bus: BusConfig = BusConfig()
    #: a driver node stops its robot when no command arrived for this many periods
    watchdog_periods: float = Field(3.0, gt=0)
    #: sim rigs: "realtime" paces on the wall clock, "lockstep" steps when a command arrives
    pace: Literal["realtime", "lockstep"] = "realtime"
    #: the automated reset procedure (detectors, steps, verification), checked by hilstack.control.reset
    reset: dict[str, Any] | None = None
    source: str | None = None


class TaskConfig(BaseModel):
    RECORDS_SOURCE: ClassVar[bool] = True  # parse_model fills ``source`` with the file path
    model_config = ConfigDict(extra="allow", frozen=True)
    task: str
    source: str | None = None


def _format_loc(loc: tuple[Any, ...]) -> str:
    out = ""
    for p in loc:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def parse_model(model: type[M], data: Any, file: str | Path | None = None) -> M:
    """Validate ``data`` into ``model``; raise ConfigError naming file and field."""
    if not isinstance(data, dict):
        raise ConfigError(file, [("", f"expected a mapping at top level, got {type(data).__name__}")])
    if getattr(model, "RECORDS_SOURCE", False) and file is not None:
        data = {**data, "source": str(file)}
    try:
        return model.model_validate(data)
    except ValidationError as e:
        problems = []
        for err in e.errors():
            msg = err["msg"]
            if err["type"] == "extra_forbidden":
                allowed = sorted(k for k in model.model_fields if k != "source")
                msg = f"unknown field (allowed here: {allowed})" if len(err["loc"]) == 1 else "unknown field"
            elif "input" in err and err["type"] != "missing":
                msg = f"{msg} (got {err['input']!r})"
            problems.append((_format_loc(err["loc"]), msg))
        raise ConfigError(file, problems) from None


def read_yaml(path: str | Path) -> Any:
    p = Path(path)
    if not p.is_file():
        raise ConfigError(p, [("", "file not found")])
    try:
        return yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(p, [(where, f"not valid YAML: {getattr(e, 'problem', e)}")]) from None


def load_yaml_model(path: str | Path, model: type[M]) -> M:
    return parse_model(model, read_yaml(path), path)


def config_path(kind: str, name_or_path: str | Path, base: Path | None = None) -> Path:
    """Resolve a config by name (``configs/<kind>/<name>.yaml``) or by path."""
    p = Path(name_or_path)
    candidates = [p] if p.suffix in (".yaml", ".yml") else []
    if base is not None and not p.is_absolute():
        candidates.insert(0, base / p)
    candidates.append(CONFIG_ROOT / kind / f"{p.name if p.suffix else p.name + '.yaml'}")
    for c in candidates:
        if c.is_file():
            return c
    known = sorted(x.stem for x in (CONFIG_ROOT / kind).glob("*.yaml"))
    raise ConfigError(str(name_or_path), [("", f"no such {kind[:-1]} config; known: {known}")])


def load_robot(name_or_path: str | Path, **overrides: Any) -> RobotConfig:
    """Load a robot config; ``backend=``/``params=`` override the file."""
    path = config_path("robots", name_or_path)
    data = dict(read_yaml(path))
    if overrides.get("backend"):
        data["backend"] = overrides["backend"]
    if overrides.get("params"):
        data["params"] = {**data.get("params", {}), **overrides["params"]}
    return parse_model(RobotConfig, data, path)


def load_rig(name_or_path: str | Path) -> RigConfig:
    return load_yaml_model(config_path("rigs", name_or_path), RigConfig)


def load_task(name_or_path: str | Path) -> TaskConfig:
    return load_yaml_model(config_path("tasks", name_or_path), TaskConfig)


def rig_robot_config(rig: RigConfig, key: str) -> RobotConfig:
    """The robot config of one rig entry, with the rig's overrides applied."""
    entry = rig.robots[key]
    base = Path(rig.source).parent if rig.source else None
    path = config_path("robots", entry.config, base)
    return load_robot(path, backend=entry.backend, params=entry.params)


# ---------------------------------------------------------------- robot-specific params
P = TypeVar("P", bound=BaseModel)


class Params(BaseModel):
    """Base of robot-specific ``params`` sections: unknown keys are errors.

    Lives here, beside the schemas, so drivers and sim backends both use it without
    depending on each other."""

    model_config = ConfigDict(extra="forbid")


class EmulatorParams(Params):
    """Shared base of every robot's ``params.emulator`` section (backend ``emulated``): how
    the driver starts the emulator process. Each robot's emulator subclasses it with its own
    typed fault options; a key no class declares (a misspelt fault option) is an error
    naming ``params.emulator.<key>``."""

    start_timeout_s: float = Field(30.0, gt=0, description="time for the emulator process to import MuJoCo, build "
                                   "its model and print where to connect [s]")
    keep_log: bool = Field(False, description="keep the emulator's log after cleanup (always kept on failure)")


def parse_params(cfg: RobotConfig, model: type[P]) -> P:
    """Validate ``cfg.params``; errors name the file and ``params.<field>``."""
    try:
        return parse_model(model, dict(cfg.params), cfg.source)
    except ConfigError as e:
        raise ConfigError(cfg.source, [(f"params.{f}" if f else "params", m) for f, m in e.problems]) from None
