"""The reset arm controller's UDP link: little-endian frames, one per datagram.

* ``RAQ1``: the host asks the controller to stream its state to the sender (sent until
  the first state arrives).
* ``RAC1`` u32 seq, 8 × f64: a command (7 joint position targets [rad], the gripper
  opening target [m]); the controller streams its state to the sender from then on.
* ``RAS1`` u32 seq, f64 t_s (controller clock), 21 × f64: the state
  (drivers/reset_arm/config.py's layout).

Anything else (wrong magic, wrong length, NaN in a command) is refused with
:class:`ProtocolError`; the controller keeps its last good command.
"""

from __future__ import annotations

import struct

import numpy as np

QUERY = b"RAQ1"
_CMD = struct.Struct("<4sI8d")
_STATE = struct.Struct("<4sId21d")


class ProtocolError(ValueError):
    """A frame that is not a valid reset-arm frame."""


def encode_command(seq: int, action: np.ndarray) -> bytes:
    return _CMD.pack(b"RAC1", seq & 0xFFFFFFFF, *np.asarray(action, dtype=np.float64).reshape(8))


def decode_command(raw: bytes) -> tuple[int, np.ndarray]:
    if len(raw) != _CMD.size or raw[:4] != b"RAC1":
        raise ProtocolError(f"not a command frame ({len(raw)} bytes, magic {raw[:4]!r})")
    _, seq, *v = _CMD.unpack(raw)
    a = np.array(v)
    if not np.all(np.isfinite(a)):
        raise ProtocolError("command with NaN/inf")
    return seq, a


def encode_state(seq: int, t_s: float, state: np.ndarray) -> bytes:
    return _STATE.pack(b"RAS1", seq & 0xFFFFFFFF, float(t_s), *np.asarray(state, dtype=np.float64).reshape(21))


def decode_state(raw: bytes) -> tuple[int, float, np.ndarray]:
    if len(raw) != _STATE.size or raw[:4] != b"RAS1":
        raise ProtocolError(f"not a state frame ({len(raw)} bytes, magic {raw[:4]!r})")
    _, seq, t, *v = _STATE.unpack(raw)
    return seq, t, np.array(v)
