"""Wake-up samples of timed waits (bus/node.py: ``Subscription``, ``_WakeTimer``).

A latest-value subscription's thread blocks in Zenoh's channel, which has no receive with a
timeout; a wait's deadline is ended by a sample put session-locally (it never leaves the
process) on the subscription's key, marked by its attachment. Every other subscriber in the
process that can match the key (FIFO recorders on ``hil/**``, the e-stop latch) leaves such
samples out with :func:`is_wake`.
"""

from __future__ import annotations

import zenoh

#: attachment of a wake-up sample (:class:`_WakeTimer`): this prefix, then the subscription's
#: id and the wait's token (8 bytes each). Messages carry no attachment (``Publisher`` sets
#: none), so a sample whose attachment is not a wake is a message like any other.
WAKE_PREFIX = b"hil/wake\x00"


def is_wake(sample: zenoh.Sample) -> bool:
    """Whether ``sample`` is a session-local wake-up of a timed wait (never a message)."""
    a = sample.attachment
    return a is not None and a.to_bytes().startswith(WAKE_PREFIX)


def wake_key(key: str) -> str:
    """A concrete key that ``key`` (maybe a wildcard expression) matches: where a wait's wake-up
    sample is put so that it lands in that subscription's channel."""
    chunks = []
    for c in key.split("/"):
        if c == "**":
            continue  # matches zero chunks
        if "*" in c:
            c = c.replace("$*", "").replace("*", "w") or "w"
        chunks.append(c)
    concrete = "/".join(chunks) or "w"
    if not zenoh.KeyExpr(key).includes(zenoh.KeyExpr(concrete)):
        raise ValueError(f"bus: no wake-up key for subscription key {key!r}")
    return concrete
