"""Fuzz harnesses of the config loaders (robot, rig, task, reset steps) and of `hil`'s
argument parsing: generated documents and argument lists, not random bytes.

Each harness takes bytes (atheris' or hypothesis') and reads them as a stream of choices
(:class:`Draw`): which robot, which fields, which values. Values come from the field's own
type and bounds (just inside, on, just past each bound, the default scaled by 0, -1,
1e12), from a palette of wrong shapes and non-finite numbers, and a few byte edits of the
YAML text reach the YAML parser's errors. So coverage-guided mutation of the bytes walks
the schemas, not the YAML syntax.

The loaders are the real ones on the real path (``parse_yaml`` → ``robot_config`` /
``rig_config`` / ``rig_robot_config`` → ``make_driver``; ``load_reset``; the Baoding task's
params; `hil`'s click parser), minus only reading the file. A *crash* is:

* any exception other than :class:`~hilstack.configs.schema.ConfigError` (click's
  ``UsageError`` for arguments, exit code 2);
* a ConfigError that is not one line naming the file and, per problem, the field;
* a config that loads with a safety value that is not finite or not within bounds: the
  spec's period outside [1 ms, 1 s], a rate limit or action limit that is not finite and
  positive, a rig's watchdog outside [1, 10] periods;
* arguments that parse with a non-finite float that `hil`'s argument check lets through.
"""

from __future__ import annotations

import contextlib
import io
import math
import re
import struct
import typing
from functools import cache
from typing import Any

import yaml

from hilstack.tools.fuzz import InvariantBroken, _check

#: the file name the generated documents pretend to come from
FUZZ_DIR = "/nonexistent/hil-fuzz"
ROBOT_FILE = f"{FUZZ_DIR}/robot.yaml"
RIG_FILE = f"{FUZZ_DIR}/rig.yaml"
TASK_FILE = f"{FUZZ_DIR}/task.yaml"


class Draw:
    """Choices read from fuzz bytes; past the end every choice is the first option."""

    def __init__(self, data: bytes):
        self.data = data
        self.i = 0

    def byte(self) -> int:
        b = self.data[self.i] if self.i < len(self.data) else 0
        self.i += 1
        return b

    def below(self, n: int) -> int:
        if n <= 1:
            return 0
        v = self.byte() if n <= 256 else self.byte() << 8 | self.byte()
        return v % n

    def pick(self, seq: typing.Sequence[Any]) -> Any:
        return seq[self.below(len(seq))]

    def chance(self, k: int) -> bool:
        """True with probability about 1/k (False past the end)."""
        return self.below(k) == k - 1

    def float64(self) -> float:
        raw = bytes(self.byte() for _ in range(8))
        return struct.unpack("<d", raw)[0]


# --------------------------------------------------------------------------- values
#: wrong shapes, wrong types, non-finite and absurd numbers: any field may get one
PALETTE: tuple[Any, ...] = (
    None, True, False, 0, 1, -1, 0.5, -0.5, 3, 2**63, -(2**63), 10**30, 1e-300, 1e300, -1e300,
    math.inf, -math.inf, math.nan, "", "x", "1e12", "inf", "nan", ".inf", "-1", "/dev/null", "tcp/127.0.0.1:7447",
    "pm/x", "a.b", "line\nbreak", "é", "a" * 300, [], [1.0, 2.0], [2.0, 1.0], [math.nan, 1.0], [[1]], {}, {"a": 1},
    {"waist": [1.0, -1.0]}, {"x": math.inf}, {1: 2}, {"": None},
)


def _leaf_types(annotation: Any) -> list[Any]:
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _leaf_types(typing.get_args(annotation)[0])
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        return [t for a in typing.get_args(annotation) for t in _leaf_types(a)]
    return [annotation]


@cache
def _field_values(fi: Any) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    return field_values(fi)


def field_values(fi: Any) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    """Values aimed at one field: ``(likely valid, edges)``. Valid: its default, its
    bounds' insides, its Literal's options; edges: on and just past each bound, the default
    scaled by 0, -1 and 1e12, the options misspelt."""
    from hilstack.tools.config_bounds import field_bounds

    ok: list[Any] = []
    edge: list[Any] = []
    d = _plain(fi.get_default(call_default_factory=True)) if not fi.is_required() else None
    if isinstance(d, (int, float)) and not isinstance(d, bool):
        ok.append(d)
        edge += [d * 0, -d, d * 1e12, d + 1, d * 2]
    elif d is not None:
        ok.append(d)
    lo, hi, _ = field_bounds(fi)
    if lo is not None and hi is not None:
        ok += [math.nextafter(lo[1], math.inf), (lo[1] + hi[1]) / 2, math.nextafter(hi[1], -math.inf)]
    for b in (lo, hi):
        if b is not None:
            v = b[1]
            edge += [v, math.nextafter(v, math.inf), math.nextafter(v, -math.inf), v * 10, -v]
    for t in _leaf_types(fi.annotation):
        if typing.get_origin(t) is typing.Literal:
            for o in typing.get_args(t):
                ok.append(o)
                edge += [f"{o}x", str(o).upper()]
    return tuple(ok), tuple(edge)


def _plain(v: Any) -> Any:
    """A default as YAML can write it (a model as its mapping, a tuple as a list)."""
    if hasattr(v, "model_dump"):
        return v.model_dump()
    if isinstance(v, (tuple, list, set, frozenset)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    return v


def gen_value(draw: Draw, fi: Any, depth: int = 0) -> Any:
    """A value for a field: aimed at it (2 in 3) or from the palette; a nested model
    (``emulator:``) gets a generated section of its own."""
    nested = [t for t in _leaf_types(fi.annotation) if isinstance(t, type) and hasattr(t, "model_fields")]
    if nested and depth < 2 and draw.chance(2):
        return gen_section(draw, nested[0], depth + 1)
    ok, edge = _field_values(fi)
    k = draw.below(16)
    if ok and k < 10:
        return draw.pick(ok)
    if edge and k < 13:
        return draw.pick(edge)
    if k == 13:
        return draw.float64()
    return draw.pick(PALETTE)


def gen_section(draw: Draw, model: Any, depth: int = 0) -> dict[Any, Any]:
    """A mapping for ``model``: some of its fields with generated values, sometimes an
    unknown key (a typo, a key with dots or a newline)."""
    fields = list(model.model_fields.items())
    out: dict[Any, Any] = {}
    for _ in range(draw.below(6)):
        if not fields:
            break
        name, fi = draw.pick(fields)
        if name == "source":
            continue
        out[name] = gen_value(draw, fi, depth)
    if draw.chance(6):
        out[draw.pick(["mas_kg", "perod_s", "a.b", "line\nbreak", 7, "", "[key]"])] = draw.pick(PALETTE)
    return out


# --------------------------------------------------------------------------- YAML text
def to_yaml(draw: Draw, doc: Any) -> str:
    """The document as YAML, sometimes with a few bytes edited (YAML's own errors)."""
    text = yaml.safe_dump(doc, allow_unicode=True, sort_keys=False)
    if draw.chance(6):
        b = bytearray(text.encode())
        for _ in range(1 + draw.below(3)):
            i = draw.below(len(b) + 1)
            op = draw.below(3)
            if op == 0 and i < len(b):
                b[i] = draw.pick(b":-[]{}&*!|>'\"%@`#,? \n\t\\")
            elif op == 1:
                b.insert(i, draw.pick(b":-[]{}&*!|\n "))
            elif i < len(b):
                del b[i]
        text = b.decode("utf-8", "replace")
    return text


# --------------------------------------------------------------------------- checks
def check_config_error(e: Any, file: str) -> None:
    """A rejection: one line per problem, naming the file and each field."""
    from hilstack.tools.common import one_line

    line = one_line(e)
    _check("\n" not in line and "\r" not in line, f"error is not one line: {line!r}")
    _check(e.file == file or e.file.startswith(FUZZ_DIR) or e.file.endswith((".yaml", ".yml")),
           f"error names file {e.file!r}, not the config")
    _check(bool(e.problems), "an error without a problem")
    for fld, msg in e.problems:
        _check(bool(fld) or "top level" in msg or "YAML" in msg or "file" in msg or "config" in msg,
               f"a problem without a field: {msg!r}")
        _check(bool(msg), f"{fld}: a problem without a message")


def check_spec(drv: Any) -> None:
    """The safety values a loaded config gives the robot are finite and in bounds."""
    import numpy as np

    sp = drv.spec
    _check(isinstance(sp.period_s, float) and 0.001 <= sp.period_s <= 1.0, f"period_s {sp.period_s!r} accepted")
    if sp.action.dim:
        lo, hi = np.asarray(sp.action.low), np.asarray(sp.action.high)
        _check(bool(np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)),
               f"action limits {lo}, {hi} accepted")
    rate = sp.action_rate_per_s
    if rate is not None:
        r = np.asarray(rate)
        _check(bool(np.all(np.isfinite(r)) and np.all(r > 0)), f"rate limit {r} accepted")


@cache
def _robot_models() -> dict[str, Any]:
    """robot name -> its params model (the one its backends validate ``params`` with)."""
    from hilstack.drivers.camera.config import CameraParams
    from hilstack.drivers.mocap.driver import MocapParams
    from hilstack.drivers.reset_arm.config import ResetArmParams
    from hilstack.drivers.sawyer.config import SawyerParams
    from hilstack.drivers.shadow_hand.config import ShadowHandParams
    from hilstack.drivers.velociroach.config import VelociRoachParams
    from hilstack.drivers.widowx.config import MechanismParams, WidowXParams
    from hilstack.sim_backends.pointmass import PointMassParams

    return {"pointmass": PointMassParams, "velociroach": VelociRoachParams, "shadow_hand": ShadowHandParams,
            "widowx": WidowXParams, "reset_mechanism": MechanismParams, "sawyer": SawyerParams,
            "camera": CameraParams, "reset_arm": ResetArmParams, "mocap": MocapParams}


#: backends whose driver needs a world another driver builds in the same process: make_driver
#: builds them, but nothing is checked beyond that
_SHIPPED_ROBOTS = ("pointmass", "velociroach", "shadow_hand", "widowx", "reset_mechanism", "sawyer", "camera",
                   "reset_arm", "mocap")


def gen_robot_doc(draw: Draw) -> Any:
    from hilstack.drivers.registry import robots

    if draw.chance(16):  # not a mapping at all
        return draw.pick([[{"robot": "pointmass"}], "pointmass", 42, None, [], True])
    robot = draw.pick(robots()) if not draw.chance(12) else draw.pick(PALETTE)
    doc: dict[Any, Any] = {"robot": robot}
    if not draw.chance(4):
        doc["backend"] = draw.pick(["sim", "emulated", "real"]) if not draw.chance(8) else draw.pick(
            ["Sim", "hardware", None, 1])
    model = _robot_models().get(robot) if isinstance(robot, str) else None
    if model is not None and not draw.chance(8):
        doc["params"] = gen_section(draw, model)
    elif draw.chance(3):
        doc["params"] = draw.pick(PALETTE)
    if draw.chance(10):
        doc[draw.pick(["sourc", "params2", "robots"])] = draw.pick(PALETTE)
    return doc


def _build(cfg: Any) -> None:
    """make_driver on a loaded robot config, then the spec check."""
    from hilstack.configs.schema import ConfigError
    from hilstack.drivers.registry import make_driver

    try:
        drv = make_driver(cfg)
    except ConfigError as e:
        check_config_error(e, cfg.source or ROBOT_FILE)
        return
    check_spec(drv)


# --------------------------------------------------------------------------- targets
def fuzz_robot_config(data: bytes) -> None:
    """A generated robot config through the loader and ``make_driver``."""
    from hilstack.configs.schema import ConfigError, parse_yaml, robot_config

    draw = Draw(data)
    text = to_yaml(draw, gen_robot_doc(draw))
    try:
        cfg = robot_config(parse_yaml(text, ROBOT_FILE), ROBOT_FILE)
    except ConfigError as e:
        check_config_error(e, ROBOT_FILE)
        return
    _build(cfg)


def gen_rig_doc(draw: Draw, reset: bool = False) -> Any:
    from hilstack.configs.schema import BusConfig, RigConfig

    bad = 24 if reset else 10  # how rarely a shape is wrong (a reset needs a rig that loads)
    if draw.chance(bad * 2):
        return draw.pick([["pm"], "rig", 3, None])
    doc: dict[Any, Any] = {}
    if not draw.chance(bad * 2):
        doc["name"] = draw.pick(["r", "lab-1"]) if not draw.chance(bad) else draw.pick(["bad name", "pm/x", "", 5])
    robots: dict[Any, Any] = {}
    for _ in range(draw.below(3) + (0 if draw.chance(bad) else 1)):
        key = draw.pick(["pm", "roach", "hand", "arm"]) if not draw.chance(bad) else draw.pick(
            ["pm/x", "a.b", "", "x y", 1, "line\nbreak"])
        name = draw.pick(_SHIPPED_ROBOTS)
        entry: dict[Any, Any] = {"config": draw.pick([name, f"{name}.yaml"]) if not draw.chance(bad) else draw.pick(
            ["no_such", "../robots/pointmass.yaml", "", 3])}
        if draw.chance(2):
            entry["backend"] = draw.pick(["sim", "emulated", "real"]) if not draw.chance(bad) else draw.pick(
                ["hardware", None])
        if draw.chance(2):
            entry["params"] = gen_section(draw, _robot_models()[name]) if not draw.chance(6) else draw.pick(PALETTE)
        if draw.chance(bad * 2):
            entry = draw.pick(PALETTE)
        robots[key] = entry
    doc["robots"] = robots if not draw.chance(bad * 2) else draw.pick(PALETTE)
    if draw.chance(2):
        doc["watchdog_periods"] = gen_value(draw, RigConfig.model_fields["watchdog_periods"])
    if draw.chance(2):
        doc["pace"] = draw.pick(["realtime", "lockstep", "lockstep", "realtime", "fast"])
    if draw.chance(5):
        doc["bus"] = gen_section(draw, BusConfig)
    if reset:
        doc["reset"] = gen_reset(draw, [k for k in robots if isinstance(k, str)])
    return doc


def _load_rig(text: str, build: bool = True) -> Any:
    """The rig through its loader and (``build``) every robot of it through ``make_driver``."""
    from hilstack.configs.schema import ConfigError, parse_yaml, rig_config, rig_robot_config

    try:
        rig = rig_config(parse_yaml(text, RIG_FILE), RIG_FILE)
    except ConfigError as e:
        check_config_error(e, RIG_FILE)
        return None
    _check(1.0 <= rig.watchdog_periods <= 10.0, f"watchdog_periods {rig.watchdog_periods!r} accepted")
    _check(all(re.fullmatch(r"[A-Za-z0-9_\-]+", k) for k in rig.robots), f"robot keys {list(rig.robots)} accepted")
    for key in rig.robots:
        cfg = rig_robot_config(rig, key)
        if build:
            _build(cfg)
    return rig


def fuzz_rig_config(data: bytes) -> None:
    """A generated rig config (robots, overrides, pace, watchdog, bus) and its robots."""
    draw = Draw(data)
    _load_rig(to_yaml(draw, gen_rig_doc(draw)))


def gen_reset(draw: Draw, robots: list[str]) -> Any:
    from hilstack.control.reset.config import DetectorConfig, StepConfig, VerifyConfig
    from hilstack.control.reset.steps import STEP_KINDS

    if draw.chance(16):
        return draw.pick(PALETTE)
    doc: dict[Any, Any] = {"robot": draw.pick(robots or ["pm"]) if not draw.chance(10) else draw.pick(["nobody", 3])}
    steps = []
    for _ in range(draw.below(4)):
        kind = draw.pick(sorted(STEP_KINDS)) if not draw.chance(10) else draw.pick(["fly", "", 1])
        s = gen_section(draw, StepConfig)
        s["kind"] = kind
        if kind in STEP_KINDS and draw.chance(2):
            s["params"] = gen_section(draw, STEP_KINDS[kind].params_model())
        steps.append(s)
    doc["steps"] = steps
    for _ in range(draw.below(3)):
        d = gen_section(draw, DetectorConfig)
        d["kind"] = draw.pick(["timeout", "arena", "tipped", "drop", "wall"])
        doc.setdefault("detectors", []).append(d)
    if draw.chance(3):
        doc["verify"] = gen_section(draw, VerifyConfig)
    if draw.chance(3):
        doc["state_timeout_s"] = draw.pick([2.0, math.inf, -1, 1e9, "x", 0])
    if draw.chance(4):
        doc["start_pose"] = draw.pick([{"x": 0.0}, {"x": math.nan}, {"yaw": 1e300}, [], "here"])
    return doc


def fuzz_reset_config(data: bytes) -> None:
    """A rig with a generated ``reset:`` section: its steps, their params, detectors."""
    from hilstack.configs.schema import ConfigError
    from hilstack.control.reset.config import load_reset

    draw = Draw(data)
    rig = _load_rig(to_yaml(draw, gen_rig_doc(draw, reset=True)), build=False)  # the robots: rig_config
    if rig is None:
        return
    try:
        cfg = load_reset(rig)
    except ConfigError as e:
        check_config_error(e, RIG_FILE)
        return
    if cfg is not None:
        _check(math.isfinite(cfg.max_duration_s()) and cfg.max_duration_s() > 0,
               f"reset of {cfg.max_duration_s()} s accepted")


def fuzz_task_config(data: bytes) -> None:
    """A generated task config: TaskConfig, then the Baoding task's own params and task."""
    from hilstack.configs.schema import ConfigError, parse_model, parse_yaml, task_config
    from hilstack.learning.baoding import BaodingTaskParams

    draw = Draw(data)
    if draw.chance(16):
        doc: Any = draw.pick(PALETTE)
    else:
        doc = {"task": draw.pick(["baoding", "path_following", "", 3])}
        doc.update(gen_section(draw, BaodingTaskParams))
        if draw.chance(3):  # a task's free keys (path_following's planner settings)
            doc[draw.pick(["path_scale", "samples", "speeds"])] = draw.pick(PALETTE)
    text = to_yaml(draw, doc)
    try:
        raw = task_config(parse_yaml(text, TASK_FILE), TASK_FILE)
        if raw.task == "baoding":
            parse_model(BaodingTaskParams, raw.model_dump(), raw.source)
    except ConfigError as e:
        check_config_error(e, TASK_FILE)


# --------------------------------------------------------------------------- CLI
#: argument values: numbers, non-finite and absurd ones, paths, names, nothing
ARG_VALUES = ("0", "1", "-1", "0.5", "3", "1e309", "-1e309", "inf", "-inf", "nan", "NaN", "1e12", "9" * 30, "",
              " ", "x", "--", "-", "-x", "--help", "pointmass", "velociroach", "pointmass_sim", "roach_emulated",
              "/dev/null", "/nonexistent/x.yaml", "a,b", "0.3,0.3", "1,2,3", "é", "line\nbreak", "true", "false")


@cache
def _cli() -> tuple[Any, list[tuple[list[str], Any]]]:
    """`hil`'s click command and every leaf command with its path (``["bench", "fuzz"]``)."""
    import typer

    from hilstack.tools.cli import app

    root = typer.main.get_command(app)
    leaves: list[tuple[list[str], Any]] = []

    def walk(cmd: Any, path: list[str]) -> None:
        subs = getattr(cmd, "commands", None)
        if subs:
            for name, sub in subs.items():
                walk(sub, [*path, name])
        else:
            leaves.append((path, cmd))

    walk(root, [])
    return root, leaves


def gen_argv(draw: Draw) -> list[str]:
    _, leaves = _cli()
    path, cmd = draw.pick(leaves)
    if draw.chance(16):
        path = [draw.pick(["nope", "bench", "--version", "--help", "", "-x"])]
    argv = list(path)
    opts = [o for p in cmd.params for o in (*p.opts, *p.secondary_opts) if o.startswith("-")]
    for _ in range(draw.below(6)):
        k = draw.below(6)
        if k <= 2 and opts:
            argv.append(draw.pick(opts))
            argv.append(draw.pick(ARG_VALUES))
        elif k == 3:
            argv.append(draw.pick(ARG_VALUES))
        elif k == 4 and opts:
            argv.append(f"{draw.pick(opts)}={draw.pick(ARG_VALUES)}")
        else:
            argv.append(draw.pick(["--nope", "-q", "--json", "--help"]))
    return argv


def parse_argv(argv: list[str]) -> tuple[Any, Any]:
    """Parse ``hil ARGV`` as `hil` does, without running the verb: (leaf command, its
    context). Raises click's UsageError (exit 2) or Exit (``--help``, ``--version``)."""
    root, _ = _cli()
    cmd, ctx = root, root.make_context("hil", list(argv))
    while getattr(cmd, "commands", None):
        args = [*getattr(ctx, "_protected_args", []), *ctx.args]
        name, sub, rest = cmd.resolve_command(ctx, args)
        cmd, ctx = sub, sub.make_context(name, rest, parent=ctx)
    return cmd, ctx


def fuzz_cli_args(data: bytes) -> None:
    """Generated `hil` argument lists: parsed (click) and checked (``user_errors``' argument
    check), as each verb sees them before it starts anything."""
    fuzz_cli_args_argv(gen_argv(Draw(data)))


def fuzz_cli_args_argv(argv: list[str]) -> None:
    """One argument list through `hil`'s parser and argument check (see :func:`fuzz_cli_args`)."""
    import typer
    from typer._click.exceptions import UsageError  # typer's own click (no public name)

    from hilstack.tools import common

    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            cmd, ctx = parse_argv(argv)
    except UsageError as e:
        _check(e.exit_code == 2, f"{argv}: usage error with exit code {e.exit_code}")
        msg = e.format_message()
        _check(isinstance(msg, str) and "Traceback" not in msg, f"{argv}: {msg!r}")
        return
    except typer.Exit:
        return  # --version
    _check(hasattr(cmd.callback, "__wrapped__") or cmd.callback is None,
           f"`hil {' '.join(argv[:2])}` is not wrapped in user_errors: a bad argument would be a traceback")
    try:
        common.check_args(ctx.params)
    except common.UserError as e:
        _check("\n" not in str(e), f"{argv}: {str(e)!r} is not one line")
        return
    for k, v in ctx.params.items():
        vals = v if isinstance(v, (list, tuple)) else [v]
        for x in vals:
            _check(not (isinstance(x, float) and not math.isfinite(x)), f"{argv}: {k}={x!r} reaches the verb")


def seeds() -> list[bytes]:
    """A few inputs of every length class (the choices are read from the start)."""
    return [bytes([i] * n) for i in range(0, 256, 37) for n in (8, 64, 256)]


__all__ = ["Draw", "InvariantBroken", "fuzz_cli_args", "fuzz_reset_config", "fuzz_rig_config", "fuzz_robot_config",
           "fuzz_task_config", "parse_argv", "seeds"]
