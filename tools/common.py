"""Shared helpers of the `hil` verbs: user-error handling, bus options, JSON output."""

from __future__ import annotations

import functools
import json
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

import typer

from hilstack.configs.schema import BusConfig, ConfigError

F = TypeVar("F", bound=Callable[..., Any])


class UserError(Exception):
    """A problem the user can fix (bad argument, missing file): one line, exit 2."""


#: ``--ray`` of the sweep commands: ``local``, a local Ray runtime (``--workers`` CPUs); an ADDRESS,
#: a running cluster (docs/scaling.md). Without it the sweep runs serially in the process.
RAY_OPTION = typer.Option(None, "--ray", metavar="local|ADDRESS",
                          help="run the sweep's tasks on Ray: 'local' starts a runtime with --workers CPUs; "
                               "an ADDRESS (ray start --head printed it) joins that cluster (docs/scaling.md)")


#: Exit codes of every `hil` verb besides 0 (docs/platform.md, "Exit codes").
EXIT_RUNTIME, EXIT_USAGE = 1, 2


def one_line(e: BaseException) -> str:
    """An exception as one line; a ConfigError keeps each file: field: problem."""
    if isinstance(e, ConfigError):
        return "; ".join(f"{e.file}: {fld or '<root>'}: {msg}" if e.file != "<inline>" else f"{fld}: {msg}"
                         for fld, msg in e.problems)
    lines = str(e).strip().splitlines()
    return lines[0] if lines else type(e).__name__


#: after an error a verb exits within this long, even when something it opened (a Zenoh
#: session's callback threads, which are not daemon threads) would keep the process alive [s]
ERROR_EXIT_GRACE_S = 5.0
#: set by the `hil` program (tools/cli.py: main); off when verbs run inside another
#: process (tests' CliRunner), which must not be ended
HARD_EXIT_AFTER_ERROR = False


def exit_within(code: int, grace_s: float = ERROR_EXIT_GRACE_S) -> None:
    """Make sure this process ends, with ``code``, at most ``grace_s`` from now: a daemon
    thread that calls ``os._exit`` if the normal exit has not happened by then. Called on
    every error path of :func:`user_errors`: no verb hangs after an error. Only in the
    `hil` program (:data:`HARD_EXIT_AFTER_ERROR`)."""
    if not HARD_EXIT_AFTER_ERROR:
        return

    def hard_exit() -> None:
        time.sleep(grace_s)
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: S110 - exiting anyway
                pass
        os._exit(code)

    threading.Thread(target=hard_exit, daemon=True, name="exit-after-error").start()
def check_args(params: dict[str, Any]) -> None:
    """Arguments every verb refuses before it starts anything: a number that is not finite
    (``--timeout-s inf`` would wait forever, ``--seconds nan`` drive for no time). Raises
    :class:`UserError` naming the option."""
    for name, v in params.items():
        for x in v if isinstance(v, (list, tuple)) else (v,):
            if isinstance(x, float) and not math.isfinite(x):
                raise UserError(f"--{name.replace('_', '-')} {x}: expected a finite number")


def user_errors(fn: F) -> F:
    """Expected failures as one line on stderr, no traceback. Exit 2: the input is wrong
    (argument, config, missing file, a command the contract refuses). Exit 1: the robot,
    its link or the rig failed while running (the robot's safety has stopped it).
    Non-finite numbers among the arguments are refused first (:func:`check_args`)."""
    from hilstack.bus.access import AccessError
    from hilstack.bus.lifetime import StopRequested
    from hilstack.bus.node import NodeConflict
    from hilstack.bus.session import BusUnavailable
    from hilstack.configs.extras import MissingExtra, install_hint, missing_extra
    from hilstack.drivers.base import CommandError, LifecycleError, LinkError

    @functools.wraps(fn)
    def wrapper(*a: Any, **kw: Any) -> Any:
        try:
            check_args(kw)
            return fn(*a, **kw)
        except (UserError, ConfigError, CommandError, FileNotFoundError, AccessError, NodeConflict) as e:
            typer.echo(f"error: {one_line(e)}", err=True)
            exit_within(EXIT_USAGE)
            raise typer.Exit(EXIT_USAGE) from None
        except ModuleNotFoundError as e:
            # an optional dependency (configs/extras.py): one line naming what installs it
            hint = e if isinstance(e, MissingExtra) else (
                missing_extra("this command", e.name) if e.name and install_hint(e.name) else None)
            if hint is None:
                raise
            typer.echo(f"error: {one_line(hint)}", err=True)
            exit_within(EXIT_USAGE)
            raise typer.Exit(EXIT_USAGE) from None
        except StopRequested as e:
            # Ctrl-C/SIGTERM during a wait (for a robot's spec...): nothing ran yet, nothing to stop
            typer.echo(f"{one_line(e)}", err=True)
            raise typer.Exit(0) from None
        except (LinkError, LifecycleError, BusUnavailable) as e:
            what = "link error" if isinstance(e, LinkError) else "error"
            typer.echo(f"{what}: {one_line(e)}", err=True)
            # what follows the first line (e.g. the emulator's log tail) is diagnosis: indented
            for ln in str(e).strip().splitlines()[1:]:
                typer.echo(f"  {ln}", err=True)
            exit_within(EXIT_RUNTIME)
            raise typer.Exit(EXIT_RUNTIME) from None
        except Exception as e:
            # typer.Exit and typer's usage errors carry their exit code (0: a normal end);
            # anything else is a bug: its traceback, exit 1, and the process still ends
            code = getattr(e, "exit_code", EXIT_RUNTIME)
            if code:
                exit_within(code)
            raise

    return wrapper  # type: ignore[return-value]


def with_endpoint(bus: BusConfig, endpoint: str | None) -> BusConfig:
    """``bus`` with its endpoint replaced (``--endpoint``); everything else, access control
    included, stays as the rig says."""
    if not endpoint:
        return bus
    try:
        return BusConfig.model_validate({**bus.model_dump(), "endpoint": endpoint})
    except Exception as e:
        raise UserError(f"bad --endpoint {endpoint!r}: {one_line(e)}") from None


def apply_sets(data: Any, sets: list[str], robots: Any = ()) -> list[tuple[str, Any]]:
    """``--set key=value`` overrides applied to a rig file's parsed YAML ``data`` (in place):
    ``key`` is a dotted path into the file (``watchdog_periods``, ``bus.endpoint``,
    ``robots.roach.params.port``; ``roach.params.port`` for short when ``roach`` is one of the
    rig's ``robots``), ``value`` is read as YAML (``5``, ``true``, ``[a, b]``, text). Nothing is
    checked here but the shape: the rig's schema (and the robot's, for ``params``) checks the
    values as it checks the file's. Returns the (path, value) pairs."""
    import yaml

    done: list[tuple[str, Any]] = []
    for item in sets:
        key, eq, text = item.partition("=")
        parts = key.strip().split(".")
        if not eq or not all(parts):
            raise UserError(f"--set {item}: expected key=value, e.g. watchdog_periods=5 or roach.params.port=/dev/ttyUSB1")
        if parts[0] in robots and parts[0] not in ("robots", "bus", "reset"):
            parts = ["robots", *parts]
        try:
            value = yaml.safe_load(text) if text.strip() else ""
        except yaml.YAMLError:
            raise UserError(f"--set {item}: the value is not valid YAML") from None
        node = data
        for i, part in enumerate(parts[:-1]):
            nxt = node.get(part) if isinstance(node, dict) else None
            if nxt is None and isinstance(node, dict):
                nxt = node[part] = {}
            if not isinstance(nxt, dict):
                raise UserError(f"--set {item}: {'.'.join(parts[:i + 1])} is not a mapping in the rig file")
            node = nxt
        node[parts[-1]] = value
        done.append((".".join(parts), value))
    return done


def rig_bus(rig: str, endpoint: str | None = None, need_config: bool = False,
            sets: list[str] | None = None) -> tuple[str, BusConfig, Any]:
    """The one way every verb that takes a rig reads it: a rig config name
    (``configs/rigs/<name>.yaml``) or file → ``(rig name, its bus settings, RigConfig)``,
    ``--endpoint`` replacing only the endpoint, ``sets`` (``--set key=value``, :func:`apply_sets`)
    changing the file's values before the schema checks them. A plain name that is no config (a rig made
    up on the command line, e.g. a test's): that name on the default bus and None, unless
    ``need_config``."""
    from pathlib import Path

    from hilstack.bus.keys import _NAME
    from hilstack.configs.schema import config_path, load_rig, read_yaml, rig_config

    try:
        path = config_path("rigs", rig)
    except ConfigError:
        p = Path(rig)
        if need_config or p.suffix in (".yaml", ".yml") or "/" in rig or not _NAME.match(rig):
            raise
        return rig, bus_config(endpoint), None
    if sets:
        data = read_yaml(path)
        if not isinstance(data, dict):
            raise ConfigError(path, [("", "a rig file is a mapping (name:, robots:, ...)")])
        apply_sets(data, sets, data.get("robots") or {})
        try:
            cfg = rig_config(data, path)
        except ConfigError as e:  # the file was fine until --set changed it: say so
            raise ConfigError(f"{path} with --set {' '.join(sets)}", e.problems) from None
    else:
        cfg = load_rig(path)
    return cfg.name, with_endpoint(cfg.bus, endpoint), cfg


def provision_credentials(rig: str, bus: BusConfig, cfg: Any) -> None:
    """A rig without real hardware whose credentials file is missing gets one (bus/access.py:
    provision), said in one line on stderr; a real rig's missing file stays an error."""
    from hilstack.bus.access import provision

    line = provision(rig, bus, [r.backend for r in cfg.robots.values()] if cfg is not None else [])
    if line:
        typer.echo(line, err=True)


def bus_config(endpoint: str | None, connect: list[str] | None = None) -> BusConfig:
    kw: dict[str, Any] = {}
    if endpoint:
        kw["endpoint"] = endpoint
    if connect:
        kw["connect"] = connect
    try:
        return BusConfig(**kw)
    except Exception as e:
        raise UserError(f"bad bus option: {e}") from None


def echo_json(obj: Any) -> None:
    sys.stdout.write(json.dumps(obj, default=_default) + "\n")
    sys.stdout.flush()


def _default(o: Any) -> Any:
    try:
        import numpy as np

        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
    except ImportError:  # pragma: no cover
        pass
    return str(o)


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


EndpointOpt = typer.Option(None, "--endpoint", help="Zenoh rendezvous endpoint (default tcp/127.0.0.1:7447)")


def config_completer(kind: str) -> Callable[[str], list[str]]:
    """Shell completion (``hil --install-completion``) of a config argument: the names under
    ``configs/<kind>/`` that start with what was typed; once it looks like a path (``/``, ``.``), the
    YAML files and folders there."""

    def complete(incomplete: str) -> list[str]:
        from pathlib import Path

        from hilstack.configs.schema import CONFIG_ROOT

        if "/" in incomplete or incomplete.startswith("."):
            folder, _, stem = incomplete.rpartition("/")
            base = Path(folder or ".")
            try:
                found = [p for p in base.iterdir() if p.name.startswith(stem)
                         and (p.is_dir() or p.suffix in (".yaml", ".yml"))]
            except OSError:
                return []
            return sorted(f"{folder}/{p.name}/" if p.is_dir() else f"{folder}/{p.name}" if folder else p.name
                          for p in found)
        return sorted(p.stem for p in (CONFIG_ROOT / kind).glob("*.yaml") if p.stem.startswith(incomplete))

    return complete


complete_rig = config_completer("rigs")
complete_robot = config_completer("robots")
