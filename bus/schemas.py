"""Typed, versioned message schemas (msgspec, MessagePack on the wire).

One definition per message. Each carries a tag naming its type and version
(``hil.RobotState/1``); decoding with the wrong type or a malformed payload raises
:class:`MalformedMessage`. A schema change that is not backward compatible bumps
the version in the tag.
"""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Callable
from typing import Any, TypeVar

import msgspec
import numpy as np


class MalformedMessage(ValueError):
    """A payload that does not decode as the expected message type."""


class Msg(msgspec.Struct, tag_field="type", kw_only=True, omit_defaults=False):
    #: sender wall clock (time.time()) at publish [s]
    stamp_s: float = 0.0
    #: per-publisher sequence number, starts at 1
    seq: int = 0


class StoppedReason(enum.StrEnum):
    """Why the driver node holds the robot's safe action (``RobotState.stopped_reason``).

    str-valued: the wire and recordings carry these very strings (the field stays ``str``,
    so a reader meets a newer reason as a string, not as an undecodable state)."""

    #: taking commands: the robot runs the newest one
    RUNNING = ""
    #: no command since activation, a reset, a teleport, an e-stop release or a resume
    WAITING = "waiting"
    #: commands stopped arriving (``watchdog_periods`` without one)
    STALE = "stale"
    #: the rig's e-stop is engaged
    ESTOP = "estop"
    #: the newest command was invalid (shape, NaN) and refused
    BAD_COMMAND = "bad_command"
    #: the reading is not ok (stale or non-finite input) or not ok long enough again
    UNHEALTHY = "unhealthy"


class ResetPhase(enum.StrEnum):
    """``ResetEvent.phase``: requests (``request`` from a controller or the supervisor on
    ``reset/request``; ``teleport`` and ``episode`` from the reset supervisor on
    ``reset/driver``) and answers (``done``, ``failed``, ``unsupported``). str-valued as
    :class:`StoppedReason`."""

    REQUEST = "request"
    TELEPORT = "teleport"
    EPISODE = "episode"
    DONE = "done"
    FAILED = "failed"
    UNSUPPORTED = "unsupported"


#: RobotState.device_t_s of a reading without a device clock
NO_DEVICE_CLOCK = -1.0


class RobotState(Msg, tag="hil.RobotState/1"):
    robot: str
    #: robot clock at measurement (wall clock for real/emulated, sim time for sim) [s]
    t_s: float
    state: list[float]
    #: the robot's own reading counter (Observation.seq)
    obs_seq: int = 0
    ok: bool = True
    active: bool = False
    #: why the driver node is holding the safe action: a :class:`StoppedReason` value
    #: ("" while it takes commands; "waiting", "stale", "estop", "bad_command", "unhealthy")
    stopped_reason: str = ""
    #: last applied action (held during the period that ended with this state)
    action: list[float] = []
    #: incremented by each completed reset; splits recordings into episodes
    episode: int = 0
    health: dict[str, Any] = {}
    #: the device's own clock when the state was sampled [s, >= 0] (Observation.device_t_s: a
    #: Dynamixel's Realtime Tick, unwrapped), NO_DEVICE_CLOCK (-1) when the device has none. Its origin
    #: is the device's; ``t_s`` stays the host's stamp. Added to version 1 with a default (older readers
    #: ignore it; one JSON type, as Foxglove's schemas need).
    device_t_s: float = -1.0


class Command(Msg, tag="hil.Command/1"):
    robot: str
    action: list[float]
    #: the state sequence number this command answers (lockstep sims step on it)
    state_seq: int = 0
    source: str = ""


class EStop(Msg, tag="hil.EStop/1"):
    """Engage (``engaged=True``) or release the rig's latched e-stop."""

    engaged: bool = True
    reason: str = ""
    source: str = ""
    #: unique id of this command (repeats of one command share it); acks quote it
    id: str = ""
    #: who sent it: the sender's bus identity (its credentials' user on a rig with access control,
    #: else the OS user). Receivers of a release set it from the release key (bus/keys.py:
    #: estop_release), which the rig's ACL binds to the credentials. Added to version 1 with a
    #: default (additive: older readers ignore it, older messages read as "")
    sender: str = ""


class EStopAck(Msg, tag="hil.EStopAck/1"):
    """A driver node's answer to an ``EStop``: the state its robot is now in."""

    #: the driver node's name (``driver-<robot>``)
    node: str
    robot: str
    #: True: stopped and refusing commands; False: released (active again)
    engaged: bool
    #: ``EStop.id`` of the command answered
    estop_id: str = ""
    detail: str = ""
    #: engaged and the device itself confirmed its safe state (``Driver.stop_confirmed``:
    #: e.g. the servos read back the stop); False when the stop could not be verified
    #: (a frozen device) or for a release
    device_confirmed: bool = False


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
    #: the planner's sample count for this plan (0: not a sampling planner); on a wall-clock
    #: rig it follows the load (hilstack.control.sample_refit)
    samples: int = 0


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


class ModelUpdate(Msg, tag="hil.ModelUpdate/2"):
    """An online-adapted dynamics model, from the adaptation node to the MPC, on
    ``hil/<rig>/model/update`` (learning/adaptation/node.py, docs/adaptation.md "On the bus").

    Tensors travel as one buffer of raw little-endian float32 (``data``, C order, in the
    order of ``names``) with their names and shapes beside it: no per-element encoding, one
    copy on each side, and :meth:`tensors` checks the whole buffer for NaN/inf in one pass.
    ``kind`` says what the tensors are: ``full`` (every adapted parameter), ``subset``
    (some of them, e.g. the last layer; the rest stay the meta-learned θ*) or ``context``
    (a latent such as ReBAL's GRU state ``h``). Version 1 (model name + checkpoint path)
    was never published by any node and is gone.
    """

    #: the adaptation method (``grbal``, ``rebal``, ``mb_de``, ``mole``, ``mb``)
    method: str
    kind: str = "full"
    #: the adapter's own update counter
    update_seq: int = 0
    #: ``RobotState.stamp_s`` (sender wall clock) of the newest state the update used [ns];
    #: the reference of the state → model delay
    state_stamp_ns: int = 0
    #: ``RobotState.seq`` and episode of that state
    state_seq: int = 0
    episode: int = 0
    names: list[str] = []
    #: one shape per name (C order)
    shapes: list[list[int]] = []
    #: the tensors, concatenated: little-endian float32
    data: bytes = b""
    #: method-specific extras (scalars, e.g. the inner step size or a loss) [free form]
    info: dict[str, Any] = {}

    @classmethod
    def pack(cls, tensors: dict[str, Any], **fields: Any) -> ModelUpdate:
        """A message carrying ``tensors`` (name → array-like, cast to float32)."""
        arrays = [np.ascontiguousarray(v, dtype="<f4") for v in tensors.values()]
        return cls(names=list(tensors), shapes=[list(a.shape) for a in arrays],
                   data=b"".join(a.tobytes() for a in arrays), **fields)

    def tensors(self, expected: dict[str, tuple[int, ...]] | None = None) -> dict[str, Any]:
        """The tensors as float32 arrays (views of one copy of ``data``), validated.

        Raises :class:`MalformedMessage` (one line naming the problem) when names and
        shapes do not match the buffer, a value is NaN or inf, or, with ``expected``
        (name → shape of what the receiver's model has), a name is unknown, a shape
        differs, or a ``full`` update lacks a tensor.
        """
        where = f"model update {self.method}#{self.update_seq}"
        if len(self.names) != len(self.shapes):
            raise MalformedMessage(f"{where}: {len(self.names)} names but {len(self.shapes)} shapes")
        if len(set(self.names)) != len(self.names):
            raise MalformedMessage(f"{where}: repeated tensor names {sorted(self.names)}")
        if self.kind not in UPDATE_KINDS:
            raise MalformedMessage(f"{where}: kind {self.kind!r} is not one of {UPDATE_KINDS}")
        sizes = []
        for name, shape in zip(self.names, self.shapes, strict=True):
            if any(not 0 <= d < 2**31 for d in shape):
                raise MalformedMessage(f"{where}: tensor {name!r} has a dimension out of range: {shape}")
            sizes.append(math.prod(shape))
        if 4 * sum(sizes) != len(self.data):
            raise MalformedMessage(
                f"{where}: shapes need {4 * sum(sizes)} bytes of float32, the buffer has {len(self.data)}")
        # one copy: the arrays are writable (torch takes them as they are) and never alias the message
        flat = np.frombuffer(self.data, dtype="<f4").copy()
        if not np.isfinite(flat).all():
            bad = int(np.flatnonzero(~np.isfinite(flat))[0])
            name = self.names[int(np.searchsorted(np.cumsum(sizes), bad, side="right"))]
            raise MalformedMessage(f"{where}: tensor {name!r} has NaN or inf values")
        if expected is not None:
            for name, shape in zip(self.names, self.shapes, strict=True):
                if name not in expected:
                    raise MalformedMessage(f"{where}: unknown tensor {name!r} (the model has {sorted(expected)})")
                if tuple(shape) != tuple(expected[name]):
                    raise MalformedMessage(
                        f"{where}: tensor {name!r} has shape {tuple(shape)}, the model expects {tuple(expected[name])}")
            if self.kind == "full" and set(self.names) != set(expected):
                missing = sorted(set(expected) - set(self.names))
                raise MalformedMessage(f"{where}: a full update lacks tensors {missing}")
        out, at = {}, 0
        for name, shape, n in zip(self.names, self.shapes, sizes, strict=True):
            out[name] = flat[at : at + n].reshape(shape)
            at += n
        return out


#: what a :class:`ModelUpdate` carries (see there)
UPDATE_KINDS = ("full", "subset", "context")


class TaskPosterior(Msg, tag="hil.TaskPosterior/1"):
    """MOLe's posterior over its tasks after an EM step, on ``hil/<rig>/model/posterior``
    (recorded and plotted: one number per task)."""

    method: str
    update_seq: int = 0
    #: as in :class:`ModelUpdate` [ns]
    state_stamp_ns: int = 0
    state_seq: int = 0
    #: P(task | data) per task, in creation order (sums to 1)
    posterior: list[float] = []
    #: the most probable task (index into ``posterior``)
    task: int = 0
    #: tasks created so far (``len(posterior)`` unless tasks were merged or dropped)
    tasks_created: int = 0


class ResetEvent(Msg, tag="hil.ResetEvent/1"):
    """Reset protocol: a controller or the reset supervisor sends ``phase="request"``
    (``pose``: where to put the robot, when the backend can) on ``reset/request``;
    the driver node answers on ``reset/done`` with ``"done"``, ``"failed"`` or
    ``"unsupported"`` (:class:`ResetPhase`)."""

    robot: str
    #: a :class:`ResetPhase` value
    phase: str
    pose: dict[str, float] = {}
    episode: int = 0
    detail: str = ""
    #: a request's: the sequence number of the newest state its sender saw (the last state of
    #: the episode it ends); a driver node's answer to a teleport or a new episode: the sequence
    #: number of the first state after it (the answer and that state come through different
    #: subscriptions, whose order on arrival is not the order they were sent in); -1 unknown
    state_seq: int = -1
    #: a request's: its sender knows the rig has a reset supervisor (a ``reset:`` section) and
    #: expects it to serve the request; the driver node then never serves it itself, also while
    #: it has not seen the supervisor's liveliness token yet (it waits for it, bounded). False
    #: (recordings from before the field): served by the driver node when no supervisor is alive
    supervised: bool = False


class ResetTransition(Msg, tag="hil.ResetTransition/1"):
    """One transition of the reset supervisor's state machine (control/reset), published
    on ``reset/transition`` and recorded, so a recording says why each episode ended and
    how its reset went."""

    robot: str
    #: the machine's trigger (``end_episode``, ``pause``, ``begin``, ``retry``, ``fail``, ``estop``...)
    trigger: str
    source: str
    dest: str
    #: why the episode ended (detector name or ``request``), for the transitions of one reset
    reason: str = ""
    #: the reset step running (``drive_to_start``...), and its attempt (1 = first)
    step: str = ""
    attempt: int = 0
    #: the robot's episode counter when the transition happened
    episode: int = 0
    #: what failed, for the operator (one line)
    detail: str = ""
    #: the robot's newest state at the transition; for ``end_episode``, the ended episode's last
    #: state (a recording splits its episodes by it, whatever order the messages arrived in); -1 unknown
    state_seq: int = -1


class Ping(Msg, tag="hil.Ping/1"):
    """Benchmarks and link checks."""

    data: bytes = b""


ALL_TYPES: tuple[type[Msg], ...] = (
    RobotState, Command, EStop, EStopAck, Plan, Image, SpecMsg, ModelUpdate, TaskPosterior, ResetEvent, ResetTransition,
    Ping,
)
AnyMsg = (
    RobotState | Command | EStop | EStopAck | Plan | Image | SpecMsg | ModelUpdate | TaskPosterior | ResetEvent
    | ResetTransition | Ping
)

T = TypeVar("T", bound=Msg)

_encoder = msgspec.msgpack.Encoder()
_decoders: dict[Any, msgspec.msgpack.Decoder] = {}

#: ``encode(msg) -> bytes``: msgspec's own method, so that a publish runs no Python frame of ours
#: (the bus's hot path, `hil bench bus`)
encode = _encoder.encode

#: what msgspec raises on a payload that is not the expected type: UnicodeDecodeError comes out
#: for a string field (the type tag too) that is not UTF-8 (found by fuzzing, tools/fuzz.py)
DECODE_ERRORS = (msgspec.DecodeError, msgspec.ValidationError, UnicodeDecodeError)


def decoder(typ: type[T] | Any = AnyMsg) -> Callable[[bytes], T]:
    """msgspec's decode for ``typ`` (one decoder per type): :func:`decode` without its Python
    frame, for a hot path; it raises one of :data:`DECODE_ERRORS` on bad data, which
    :func:`malformed` turns into the :class:`MalformedMessage` :func:`decode` raises."""
    dec = _decoders.get(typ)
    if dec is None:
        dec = _decoders[typ] = msgspec.msgpack.Decoder(typ)
    return dec.decode


def malformed(typ: type[T] | Any, error: Exception) -> MalformedMessage:
    """The :class:`MalformedMessage` for a payload that failed to decode as ``typ`` with ``error``."""
    return MalformedMessage(f"not a valid {getattr(typ, '__name__', 'message')}: {error}")


def decode(data: bytes, typ: type[T] | Any = AnyMsg) -> T:
    try:
        return decoder(typ)(data)
    except DECODE_ERRORS as e:
        raise malformed(typ, e) from None


def type_name(typ: type[Msg]) -> str:
    return typ.__struct_config__.tag


# --------------------------------------------------------------------------- JSON (MCAP)
# Recordings store messages as JSON with a JSON Schema per type. The schema is written
# in the subset Foxglove's JSON-schema parser accepts (studio
# packages/mcap-support/src/parseJsonSchema.ts): a root {"type": "object",
# "properties": ...}, a "type" on every field (an enum gets the type of its values),
# "properties" on every object (free-form dicts get an empty one) and no array directly
# inside an array. Such a nested array (Plan.actions [H][A]) is recorded as an array of
# row objects {"values": [...]}; the schema drives both the wrapping and the unwrapping.

#: a row of a list-of-lists field, as recorded: {"values": [...]}
ROW_KEY = "values"
_ROW_MARK = "x-hil-row"
_JSON_TYPE_OF = {str: "string", bool: "boolean", int: "integer", float: "number"}
_SCALARS = {"string", "number", "integer", "boolean"}


class _Codec:
    """The recorded JSON form of one message type: its schema and (de)serialisation."""

    def __init__(self, typ: type[Msg]):
        self.typ = typ
        self.schema = _foxglove_schema(msgspec.json.schema(typ), type_name(typ))
        # messages without nested arrays encode directly (the fast, common path)
        self.wraps = _has_rows(self.schema)

    def encode(self, msg: Msg) -> bytes:
        if not self.wraps:
            return _json_encoder.encode(msg)
        return _json_encoder.encode(_wrap_rows(msgspec.to_builtins(msg), self.schema))

    def decode(self, data: bytes) -> Msg:
        if not self.wraps:
            try:
                return msgspec.json.decode(data, type=self.typ)
            except msgspec.ValidationError:
                pass  # e.g. a NaN recorded as null: restore below
        try:
            obj = msgspec.json.decode(data)
            return msgspec.convert(_restore(obj, self.schema), self.typ)
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            raise MalformedMessage(f"not a valid recorded {type_name(self.typ)}: {e}") from None


def _foxglove_schema(node: dict[str, Any], where: str, defs: dict[str, Any] | None = None) -> dict[str, Any]:
    """msgspec's JSON Schema rewritten into the subset Foxglove parses (see above)."""
    if defs is None:
        defs = node.get("$defs", {})
    if "$ref" in node:
        target = defs[node["$ref"].rsplit("/", 1)[-1]]
        node = {**target, **{k: v for k, v in node.items() if k not in ("$ref", "$defs")}}
    out = {k: v for k, v in node.items() if k in ("title", "description", "required", "default", "contentEncoding")}
    typ = node.get("type")
    if "enum" in node:
        kinds = {_JSON_TYPE_OF.get(type(v)) for v in node["enum"]}
        if len(kinds) != 1 or None in kinds:
            raise ValueError(f"{where}: enum {node['enum']} mixes types; Foxglove needs one")
        typ = kinds.pop()
        out["enum"] = node["enum"]
    if typ in _SCALARS:
        out["type"] = typ
    elif typ == "object":
        props = node.get("properties", {})
        out["type"] = "object"
        out["properties"] = {k: _foxglove_schema(v, f"{where}.{k}", defs) for k, v in props.items()}
        extra = node.get("additionalProperties")
        if isinstance(extra, dict) and extra.get("type") in _SCALARS:
            out["additionalProperties"] = {"type": extra["type"]}
    elif typ == "array":
        items = _foxglove_schema(node.get("items", {}), f"{where}[]", defs)
        if items.get("type") == "array":
            items = {"type": "object", _ROW_MARK: True, "properties": {ROW_KEY: items}, "required": [ROW_KEY]}
        out["type"] = "array"
        out["items"] = items
    else:
        raise ValueError(f"{where}: JSON Schema {node} has no single type; Foxglove cannot parse it")
    return out


def _has_rows(schema: dict[str, Any]) -> bool:
    if schema.get(_ROW_MARK):
        return True
    return any(_has_rows(v) for v in schema.get("properties", {}).values()) or (
        "items" in schema and _has_rows(schema["items"])
    )


def _wrap_rows(obj: Any, schema: dict[str, Any]) -> Any:
    t = schema.get("type")
    if t == "object" and isinstance(obj, dict):
        props = schema["properties"]
        return {k: _wrap_rows(v, props[k]) if k in props else v for k, v in obj.items()}
    if t == "array" and isinstance(obj, list):
        items = schema["items"]
        if items.get(_ROW_MARK):
            inner = items["properties"][ROW_KEY]
            return [{ROW_KEY: _wrap_rows(row, inner)} for row in obj]
        return [_wrap_rows(v, items) for v in obj]
    return obj


def _restore(obj: Any, schema: dict[str, Any]) -> Any:
    """Undo :func:`_wrap_rows` (plain nested lists of older files pass through) and turn
    the ``null`` that JSON makes of NaN/inf back into NaN where a number is expected."""
    t = schema.get("type")
    if t == "number" and obj is None:
        return math.nan
    if t == "object" and isinstance(obj, dict):
        props = schema["properties"]
        return {k: _restore(v, props[k]) if k in props else v for k, v in obj.items()}
    if t == "array" and isinstance(obj, list):
        items = schema["items"]
        if items.get(_ROW_MARK):
            inner = items["properties"][ROW_KEY]
            return [_restore(row[ROW_KEY] if isinstance(row, dict) else row, inner) for row in obj]
        return [_restore(v, items) for v in obj]
    return obj


_json_encoder = msgspec.json.Encoder()
_codecs: dict[type[Msg], _Codec] = {}


def _codec(typ: type[Msg]) -> _Codec:
    c = _codecs.get(typ)
    if c is None:
        c = _codecs[typ] = _Codec(typ)
    return c


def json_schema(typ: type[Msg]) -> dict[str, Any]:
    """JSON Schema of ``typ`` as recorded in MCAP (jsonschema encoding, Foxglove-parsable)."""
    return _codec(typ).schema


def encode_json(msg: Msg) -> bytes:
    """The recorded JSON form of ``msg`` (matches :func:`json_schema`)."""
    return _codec(type(msg)).encode(msg)


def decode_json(data: bytes, typ: type[T]) -> T:
    """Inverse of :func:`encode_json`; raises :class:`MalformedMessage` on bad data."""
    return _codec(typ).decode(data)  # type: ignore[return-value]


def now_s() -> float:
    return time.time()
