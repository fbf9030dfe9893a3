"""Shared helpers of the `hil` verbs: user-error handling, bus options, JSON output."""

from __future__ import annotations

import functools
import json
import logging
import sys
from collections.abc import Callable
from typing import Any, TypeVar

import typer

from configs.schema import BusConfig, ConfigError

F = TypeVar("F", bound=Callable[..., Any])


class UserError(Exception):
    """A problem the user can fix (bad argument, missing file): one line, exit 2."""


def user_errors(fn: F) -> F:
    """Turn expected failures into a one-line message and exit code 2 (no traceback)."""
    from drivers.base import CommandError, LifecycleError, LinkError

    @functools.wraps(fn)
    def wrapper(*a: Any, **kw: Any) -> Any:
        try:
            return fn(*a, **kw)
        except (UserError, ConfigError, CommandError, LinkError, LifecycleError, FileNotFoundError) as e:
            typer.echo(f"error: {e}", err=True)
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


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
