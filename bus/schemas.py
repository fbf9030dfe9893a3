"""Typed, versioned message schemas (msgspec, MessagePack on the wire).

One definition per message. Each carries a tag naming its type and version
(``hil.RobotState/1``); decoding with the wrong type or a malformed payload raises
:class:`MalformedMessage`. A schema change that is not backward compatible bumps
the version in the tag.
"""

from __future__ import annotations

import time
from typing import Any, TypeVar

import msgspec


class MalformedMessage(ValueError):
    """A payload that does not decode as the expected message type."""


class Msg(msgspec.Struct, tag_field="type", kw_only=True, omit_defaults=False):
    #: sender wall clock (time.time()) at publish [s]
    stamp_s: float = 0.0
    #: per-publisher sequence number, starts at 1
    seq: int = 0


class RobotState(Msg, tag="hil.RobotState/1"):
    robot: str
    #: robot clock at measurement (wall clock for real/emulated, sim time for sim) [s]
    t_s: float
    state: list[float]
    #: the robot's own reading counter (Observation.seq)
    obs_seq: int = 0
    ok: bool = True
    active: bool = False
    #: why the driver node is holding the safe action: "", "stale", "estop", "error"
    stopped_reason: str = ""
    #: last applied action (held during the period that ended with this state)
    action: list[float] = []
    #: incremented by each completed reset; splits recordings into episodes
    episode: int = 0
    health: dict[str, Any] = {}


class Command(Msg, tag="hil.Command/1"):
    robot: str
    action: list[float]
    #: the state sequence number this command answers (lockstep sims step on it)
    state_seq: int = 0
    source: str = ""


class EStop(Msg, tag="hil.EStop/1"):
    engaged: bool = True
    reason: str = ""
    source: str = ""


class Plan(Msg, tag="hil.Plan/1"):
    robot: str
    #: planned actions [H][A]
    actions: list[list[float]]
    #: predicted states [H+1][S] (ensemble mean), may be empty
    states: list[list[float]] = []
    cost: float = 0.0
    plan_time_s: float = 0.0
    late: bool = False
    late_count: int = 0


class Image(Msg, tag="hil.Image/1"):
    camera: str
    t_s: float
    width: int
    height: int
    encoding: str = "rgb8"
    data: bytes = b""


class SpecMsg(Msg, tag="hil.Spec/1"):
    robot: str
    spec: dict[str, Any]


class ModelUpdate(Msg, tag="hil.ModelUpdate/1"):
    model: str
    version: int
    path: str = ""
    metrics: dict[str, float] = {}


class ResetEvent(Msg, tag="hil.ResetEvent/1"):
    """Reset protocol: a controller or the reset supervisor sends ``phase="request"``
    (``pose``: where to put the robot, when the backend can) on ``reset/request``;
    the driver node answers on ``reset/done`` with ``"done"`` or ``"unsupported"``."""

    robot: str
    phase: str
    pose: dict[str, float] = {}
    episode: int = 0
    detail: str = ""


class Ping(Msg, tag="hil.Ping/1"):
    """Benchmarks and link checks."""

    data: bytes = b""


ALL_TYPES: tuple[type[Msg], ...] = (RobotState, Command, EStop, Plan, Image, SpecMsg, ModelUpdate, ResetEvent, Ping)
AnyMsg = RobotState | Command | EStop | Plan | Image | SpecMsg | ModelUpdate | ResetEvent | Ping

T = TypeVar("T", bound=Msg)

_encoder = msgspec.msgpack.Encoder()
_decoders: dict[Any, msgspec.msgpack.Decoder] = {}


def encode(msg: Msg) -> bytes:
    return _encoder.encode(msg)


def decode(data: bytes, typ: type[T] | Any = AnyMsg) -> T:
    dec = _decoders.get(typ)
    if dec is None:
        dec = _decoders[typ] = msgspec.msgpack.Decoder(typ)
    try:
        return dec.decode(data)
    # msgspec lets UnicodeDecodeError out for a string field (the type tag too) that is not
    # UTF-8 (found by fuzzing, tools/fuzz.py)
    except (msgspec.DecodeError, msgspec.ValidationError, UnicodeDecodeError) as e:
        name = getattr(typ, "__name__", "message")
        raise MalformedMessage(f"not a valid {name}: {e}") from None


def type_name(typ: type[Msg]) -> str:
    return typ.__struct_config__.tag


def json_schema(typ: type[Msg]) -> dict[str, Any]:
    return msgspec.json.schema(typ)


def now_s() -> float:
    return time.time()
