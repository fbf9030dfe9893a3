"""Typed config schemas (pydantic), validated at the edge with file+field errors."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, TypeVar

import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    field_validator,
    model_validator,
)

CONFIG_ROOT = Path(__file__).resolve().parent

M = TypeVar("M", bound=BaseModel)


def _one_line(text: str, limit: int = 300) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


class ConfigError(ValueError):
    """A config that cannot be used. ``str()`` names file, field and expectation."""

    def __init__(self, file: str | Path | None, problems: list[tuple[str, str]]):
        self.file = _one_line(str(file)) if file is not None else "<inline>"
        # one line each, whatever the input held (a key with a newline, a huge value)
        self.problems = [(_one_line(fld), _one_line(msg)) for fld, msg in problems]
        lines = [f"{self.file}: {fld or '<root>'}: {msg}" for fld, msg in self.problems]
        super().__init__("invalid config\n  " + "\n  ".join(lines))


# ---------------------------------------------------------------- bounded values
@dataclass(frozen=True)
class Bound:
    """Why a config value has the bounds it has: the physical limit they come from. Kept
    in the field's metadata (docs/platform.md, "Bounded configuration values", lists them;
    tests/test_configs.py checks every safety field carries one)."""

    source: str


def finite(*, gt: float | None = None, ge: float | None = None, lt: float | None = None,
           le: float | None = None, source: str) -> Any:
    """The type of a finite float within bounds: ``x: finite(gt=0, le=20, source="...") = 15.0``.

    NaN and ±inf are refused, and so is anything outside the bounds, with an error naming
    the file and the field (``ConfigError``). Every safety value (rate, velocity and
    acceleration limits, watchdogs, staleness and failure deadlines, periods, timeouts)
    uses this or one of the named types below; ``source`` says what physical limit the
    bounds come from. To tighten a shared type for one robot, make a new type with
    :func:`finite` (a ``Field(le=...)`` on top of an annotated type does not tighten it)."""
    if (gt is None) == (ge is None) or (lt is None) == (le is None):
        raise TypeError("finite() takes exactly one lower bound (gt or ge) and one upper bound (lt or le)")
    return Annotated[float, Field(gt=gt, ge=ge, lt=lt, le=le, allow_inf_nan=False), Bound(source)]


def bounded_int(*, ge: int, le: int, source: str) -> Any:
    """The type of an int within ``[ge, le]`` (a count of periods, of retries)."""
    return Annotated[int, Field(ge=ge, le=le), Bound(source)]


#: a control period [s]
PeriodS = finite(ge=0.001, le=1.0, source=(
    "≥ 1 ms: the host's cycle timer (bus/cycle.py) and the links carry no faster loop (a Dynamixel sync read at "
    "1 Mbit/s, a CAN burst at 1 Mbit/s take about 1 ms); ≤ 1 s: ten times the slowest control loop in the stack "
    "(10 Hz), so a tick, `hil drive` and the bridge's watchdog stay within seconds"))
#: how old an input may be and still count as fresh [s]
StaleS = finite(gt=0, le=2.0, source=(
    "≤ 2 s: at its top speed (1.36 m/s at 15 rev/s) the fastest robot, the VelociRoACH, covers 2.7 m in 2 s, "
    "more than its arena's radius; a 10 Hz controller acting on a state 20 periods old is open loop"))
#: the bound of every failure deadline [s] (FailAfterS; a count of periods times the period too)
FAIL_AFTER_MAX_S = 10.0
#: how long a device (or a link) may stay silent before the driver takes the error path [s]
FailAfterS = finite(gt=0, le=FAIL_AFTER_MAX_S, source=(
    "≤ 10 s: every device stops itself long before (firmware watchdogs 0.5 s, intera 0.2 s); beyond 10 s the "
    "host waits on a dead device instead of reporting it"))
#: how long a robot runs its last command without hearing from the host (firmware and driver watchdogs) [s]
WatchdogS = finite(gt=0, le=2.0, source=(
    "≤ 2 s: the distance a robot covers on its last command before its watchdog stops it; at 2 s the "
    "VelociRoACH at top speed (1.36 m/s) is 2.7 m away, past its arena's radius"))
#: start-up, connection and procedure timeouts (nothing moves while they run, or a watchdog guards it) [s]
TimeoutS = finite(gt=0, le=600.0, source=(
    "≤ 600 s: a start-up (an emulator building its MuJoCo model on a loaded machine: up to a minute), a "
    "connection or a reset step (the hand's arm pick-and-place: 90 s) that takes 10 minutes is hung"))
#: a rate of a stream or a loop [Hz]
RateHz = finite(ge=0.1, le=1000.0, source=(
    "≤ 1 kHz: the fastest device loop (the roach firmware's and the hand's joint loops run at 1 kHz); ≥ 0.1 Hz: "
    "a slower stream is stale by every deadline (≤ 2 s)"))
#: a count of control periods (link timeouts) [1]
Periods = bounded_int(ge=1, le=10_000, source=(
    "≥ 1 period; the count times the robot's period_s ≤ 10 s, the failure deadline's bound (FailAfterS; "
    "checked by Params for every *_periods field)"))
#: a duration of the emulators' fault injection or sim pacing (not a safety value) [s]
EmulatorS = finite(ge=0, le=3600.0, source="≤ 1 h: an emulator run's fault injection (not a safety value)")


def _ordered(r: tuple[float, float]) -> tuple[float, float]:
    if not r[0] < r[1]:
        raise ValueError(f"low {r[0]:g} must be below high {r[1]:g}")
    return r


#: a (low, high) joint range [rad], finite, low < high; each robot checks it against its hardware
JointRangeRad = Annotated[
    tuple[Annotated[float, Field(ge=-2 * 3.141592653589793, le=2 * 3.141592653589793, allow_inf_nan=False)],
          Annotated[float, Field(ge=-2 * 3.141592653589793, le=2 * 3.141592653589793, allow_inf_nan=False)]],
    AfterValidator(_ordered),
    Bound("within ±2π (one turn each way: no joint of the stack turns further) and low < high; each robot "
          "also keeps it inside its hardware's range")]


class Strict(BaseModel):
    """Base of the rig-level schemas: unknown keys are errors, floats are finite."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


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
    #: users that may run the rig's driver nodes when a separate router (``bus.router``, ``hil
    #: router``) owns the bus: they publish the robots' states; the first is the driver nodes' user
    drive: list[str] = Field(default_factory=lambda: ["driver"], min_length=1)

    @field_validator("command", "release", "drive")
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
    A lab spreads nodes over hosts with ``router`` (``tcp/10.0.0.2:7447``): ``hil router RIG``
    listens there (with ``access``: authentication and the rig's ACL) and every node, the
    driver nodes too, is its client (docs/scaling.md)."""

    mode: Literal["peer", "client"] = "peer"
    endpoint: str = "tcp/127.0.0.1:7447"
    #: the endpoint of the rig's own Zenoh router (``hil router``); every node is its client
    router: str | None = None
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

    @field_validator("router")
    @classmethod
    def _router(cls, v: str | None) -> str | None:
        return v if v is None else _check_endpoint(v)


def _check_endpoint(e: str) -> str:
    if not re.match(r"^(tcp|udp|tls|quic|unixsock-stream|ws)/.+", e):
        raise ValueError(f"endpoint {e!r} must look like 'tcp/127.0.0.1:7447'")
    return e


@dataclass(frozen=True)
class RigOverride:
    """What a rig entry changed in a robot config: ``robots.<key>`` of ``file``."""

    file: str | None
    key: str
    params: frozenset[str]
    backend: bool


class RobotConfig(BaseModel):
    """One robot. ``params`` are validated by the robot's own settings class."""
    RECORDS_SOURCE: ClassVar[bool] = True  # parse_model fills ``source`` with the file path

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    robot: str
    backend: Literal["real", "emulated", "sim"] = "sim"
    #: robot-specific parameters (sim model, port, limits...), checked by the robot package
    params: dict[str, Any] = Field(default_factory=dict)
    #: the file it came from, for error messages
    source: str | None = None
    #: set by :func:`rig_robot_config`: which rig entry overrode what (errors then name the rig file)
    _rig_override: RigOverride | None = PrivateAttr(None)


#: a robot's name on a rig: a segment of its bus keys (hil/<rig>/<robot>/state)
_KEY_SEGMENT = r"^[A-Za-z0-9_\-]+$"


class RigRobot(Strict):
    config: str = Field(min_length=1)
    backend: Literal["real", "emulated", "sim"] | None = None
    params: dict[str, Any] = Field(default_factory=dict)


#: the bridge's watchdog, in control periods of the robot
WatchdogPeriods = finite(ge=1.0, le=10.0, source=(
    "≥ 1: a command per period keeps the robot going, fewer would stop it between commands; ≤ 10: at the 10 Hz "
    "robots that is 1 s, twice their firmware watchdogs (0.5 s): the bridge stops the robot within the "
    "firmware's order of time, not only when the firmware does"))


class RigConfig(Strict):
    RECORDS_SOURCE: ClassVar[bool] = True  # parse_model fills ``source`` with the file path
    name: str = Field(pattern=_KEY_SEGMENT)
    #: at least one; each key is the robot's name on the bus (letters, digits, '_' and '-')
    robots: dict[str, RigRobot]
    bus: BusConfig = BusConfig()
    #: a driver node stops its robot when no command arrived for this many periods
    watchdog_periods: WatchdogPeriods = 3.0
    #: sim rigs: "realtime" paces on the wall clock, "lockstep" steps when a command arrives
    pace: Literal["realtime", "lockstep"] = "realtime"
    #: the automated reset procedure (detectors, steps, verification), checked by hilstack.control.reset
    reset: dict[str, Any] | None = None
    source: str | None = None

    @field_validator("robots")
    @classmethod
    def _robot_keys(cls, v: dict[str, RigRobot]) -> dict[str, RigRobot]:
        if not v:
            raise ValueError("a rig needs at least one robot (robots: {name: {config: ...}})")
        for k in v:
            if not re.match(_KEY_SEGMENT, k):
                raise ValueError(f"robot name {k!r}: use letters, digits, '_' and '-' (it is a segment of the "
                                 f"rig's bus keys, hil/<rig>/<robot>/state)")
        return v


class TaskConfig(BaseModel):
    RECORDS_SOURCE: ClassVar[bool] = True  # parse_model fills ``source`` with the file path
    model_config = ConfigDict(extra="allow", frozen=True)
    task: str
    source: str | None = None


def _format_loc(loc: tuple[Any, ...]) -> str:
    out = ""
    for p in loc:
        if isinstance(p, str) and not re.fullmatch(r"[\w\-/ ]+|\[key\]", p):  # '' too
            p = repr(p)  # a key with dots, brackets or control characters: quoted, unambiguous
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def parse_model(model: type[M], data: Any, file: str | Path | None = None) -> M:
    """Validate ``data`` into ``model``; raise ConfigError naming file and field."""
    data = _mapping(data, file)
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
            elif err["type"] == "value_error":  # our validators' own words
                msg = msg.removeprefix("Value error, ")
            elif "input" in err and err["type"] != "missing":
                got = repr(err["input"])
                msg = f"{msg} (got {got if len(got) <= 60 else got[:57] + '...'})"
            problems.append((_format_loc(err["loc"]), msg))
        raise ConfigError(file, problems) from None


def read_yaml(path: str | Path) -> Any:
    p = Path(path)
    if not p.is_file():
        raise ConfigError(p, [("", "file not found")])
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(p, [("", f"cannot read: {e}")]) from None
    return parse_yaml(text, p)


#: the most nodes a config document may expand to (aliases counted at each use)
MAX_NODES = 100_000


def parse_yaml(text: str, file: str | Path | None = None) -> Any:
    """YAML text as Python data (an empty document: ``{}``); a ConfigError naming the line.
    A recursive alias (``&a [*a]``) or a document whose aliases expand past
    :data:`MAX_NODES` (a "billion laughs") is refused: no loader walks it."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(file, [(where, f"not valid YAML: {getattr(e, 'problem', None) or e}")]) from None
    except (ValueError, TypeError, RecursionError) as e:  # e.g. an unhashable mapping key, a date out of range
        raise ConfigError(file, [("", f"not valid YAML: {type(e).__name__}: {e}")]) from None
    _check_expansion(data, file)
    return {} if data is None else data


def _check_expansion(data: Any, file: str | Path | None) -> None:
    seen, on_path = 0, set()
    stack: list[tuple[Any, bool]] = [(data, False)]
    while stack:
        v, leaving = stack.pop()
        if leaving:
            on_path.discard(id(v))
            continue
        seen += 1
        if seen > MAX_NODES:
            raise ConfigError(file, [("", f"not valid YAML for a config: its aliases expand past {MAX_NODES} nodes")])
        if isinstance(v, (dict, list)):
            if id(v) in on_path:
                raise ConfigError(file, [("", "not valid YAML for a config: a recursive alias (&x holds *x)")])
            on_path.add(id(v))
            stack.append((v, True))
            stack.extend((c, False) for c in (v.values() if isinstance(v, dict) else v))


def _mapping(data: Any, file: str | Path | None) -> dict[str, Any]:
    if not isinstance(data, dict):
        raise ConfigError(file, [("", f"expected a mapping (key: value lines) at top level, got a {_kind(data)}")])
    return data


def _kind(data: Any) -> str:
    return {list: "list", str: "string", int: "number", float: "number", bool: "boolean"}.get(
        type(data), type(data).__name__)


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
        try:
            if c.is_file():
                return c
        except (OSError, ValueError):  # a name too long for the file system, a NUL byte
            continue
    known = sorted(x.stem for x in (CONFIG_ROOT / kind).glob("*.yaml"))
    raise ConfigError(str(name_or_path), [("", f"no such {kind[:-1]} config; known: {known}")])


def load_robot(name_or_path: str | Path, **overrides: Any) -> RobotConfig:
    """Load a robot config; ``backend=``/``params=`` override the file."""
    path = config_path("robots", name_or_path)
    return robot_config(read_yaml(path), path, **overrides)


def robot_config(data: Any, file: str | Path | None = None, **overrides: Any) -> RobotConfig:
    """A robot config from parsed YAML; ``backend=``/``params=`` override it."""
    data = dict(_mapping(data, file))
    if overrides.get("backend"):
        data["backend"] = overrides["backend"]
    if overrides.get("params"):
        params = data.get("params")
        if params is not None and not isinstance(params, dict):
            raise ConfigError(file, [("params", f"expected a mapping, got a {_kind(params)}")])
        data["params"] = {**(params or {}), **overrides["params"]}
    return parse_model(RobotConfig, data, file)


def load_rig(name_or_path: str | Path) -> RigConfig:
    """Load a rig config and check it against its robots' configs (each exists and loads,
    a ``lockstep`` rig has only sim backends); errors name the rig file and field."""
    path = config_path("rigs", name_or_path)
    return rig_config(read_yaml(path), path)


def rig_config(data: Any, file: str | Path | None = None) -> RigConfig:
    rig = parse_model(RigConfig, data, file)
    for key in rig.robots:
        cfg = rig_robot_config(rig, key)
        if rig.pace == "lockstep" and cfg.backend != "sim":
            fld = f"robots.{key}.backend" if rig.robots[key].backend else "pace"
            raise ConfigError(rig.source, [(fld, f"pace 'lockstep' steps simulations; robot {key!r} has the "
                                                 f"{cfg.backend!r} backend, which runs on the wall clock: use "
                                                 f"pace: realtime or backend: sim")])
    return rig


def load_task(name_or_path: str | Path) -> TaskConfig:
    path = config_path("tasks", name_or_path)
    return task_config(read_yaml(path), path)


def task_config(data: Any, file: str | Path | None = None) -> TaskConfig:
    """A task config: its task-specific keys are free, but no number in them is inf or NaN
    (the task's own loader checks their meaning)."""
    cfg = parse_model(TaskConfig, data, file)
    bad = _nonfinite(cfg.model_extra or {}, ())
    if bad:
        raise ConfigError(file, [(_format_loc(loc), f"expected a finite number (got {v!r})") for loc, v in bad])
    return cfg


def _nonfinite(v: Any, loc: tuple[Any, ...]) -> list[tuple[tuple[Any, ...], float]]:
    if isinstance(v, float) and not math.isfinite(v):
        return [(loc, v)]
    if isinstance(v, dict):
        return [b for k, x in v.items() for b in _nonfinite(x, (*loc, k if isinstance(k, str) else repr(k)))]
    if isinstance(v, list):
        return [b for i, x in enumerate(v) for b in _nonfinite(x, (*loc, i))]
    return []


def rig_robot_config(rig: RigConfig, key: str) -> RobotConfig:
    """The robot config of one rig entry, with the rig's overrides applied. Errors in what
    the rig set name the rig file (``robots.<key>.params.<field>``), the rest the robot file."""
    entry = rig.robots[key]
    base = Path(rig.source).parent if rig.source else None
    try:
        path = config_path("robots", entry.config, base)
    except ConfigError as e:
        raise ConfigError(rig.source, [(f"robots.{key}.config", m) for _, m in e.problems]) from None
    over = RigOverride(rig.source, key, frozenset(entry.params), entry.backend is not None)
    try:
        cfg = load_robot(path, backend=entry.backend, params=entry.params)
    except ConfigError as e:
        raise blame_rig(over, e) from None
    cfg._rig_override = over
    return cfg


def blame_rig(over: RigOverride | RobotConfig | None, e: ConfigError) -> ConfigError:
    """``e`` with the problems caused by a rig's overrides named in the rig file, as
    ``robots.<key>.params.<field>`` (or ``.backend``). When some problems come from the
    robot file and some from the rig, the rig's are reported (fix those first)."""
    if isinstance(over, RobotConfig):
        over = over._rig_override
    if over is None:
        return e
    ours = []
    for fld, msg in e.problems:
        head = re.split(r"[.\[]", fld, maxsplit=2)
        if fld == "backend" and over.backend:
            ours.append((f"robots.{over.key}.backend", msg))
        elif len(head) >= 2 and head[0] == "params" and head[1] in over.params:
            ours.append((f"robots.{over.key}.{fld}", msg))
    return ConfigError(over.file, ours) if ours else e


# ---------------------------------------------------------------- robot-specific params
P = TypeVar("P", bound=BaseModel)


class Params(BaseModel):
    """Base of robot-specific ``params`` sections: unknown keys are errors.

    Lives here, beside the schemas, so drivers and sim backends both use it without
    depending on each other."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @model_validator(mode="after")
    def _periods_within_the_failure_bound(self) -> Params:
        """A deadline given in control periods (``link_timeout_periods``) is a time too:
        N · ``period_s`` ≤ :data:`FAIL_AFTER_MAX_S`, as for a deadline in seconds."""
        period = getattr(self, "period_s", None)
        if not isinstance(period, float):
            return self
        for name in type(self).model_fields:
            n = getattr(self, name)
            if name.endswith("_periods") and isinstance(n, int) and n * period > FAIL_AFTER_MAX_S:
                raise ValueError(f"{name}: {n} periods of {period:g} s = {n * period:g} s, more than the "
                                 f"{FAIL_AFTER_MAX_S:g} s a device may stay silent (FailAfterS)")
        return self


class EmulatorParams(Params):
    """Shared base of every robot's ``params.emulator`` section (backend ``emulated``): how
    the driver starts the emulator process. Each robot's emulator subclasses it with its own
    typed fault options; a key no class declares (a misspelt fault option) is an error
    naming ``params.emulator.<key>``."""

    start_timeout_s: TimeoutS = Field(30.0, description="time for the emulator process to import MuJoCo, build "
                                   "its model and print where to connect [s]")
    keep_log: bool = Field(False, description="keep the emulator's log after cleanup (always kept on failure)")


def parse_params(cfg: RobotConfig, model: type[P]) -> P:
    """Validate ``cfg.params``; errors name the file and ``params.<field>``."""
    try:
        return parse_model(model, dict(cfg.params), cfg.source)
    except ConfigError as e:
        raise ConfigError(cfg.source, [(f"params.{f}" if f else "params", m) for f, m in e.problems]) from None
