"""Fuzz harnesses for every parser of untrusted bytes, and the runner of `hil bench fuzz`.

Parsers (bytes from a radio, a serial port or the network):

* ``xbee``: :class:`hilstack.drivers.velociroach.link.XBeeDeframer` (byte stream -> XBee API frames);
* ``mavlink``: :class:`hilstack.drivers.velociroach.mavlink.MavDecoder` (XBee payload -> MAVLink
  message). Half of the inputs get a valid MAVLink CRC, so the fuzzer also reaches the
  payload unpacking behind the CRC check (a random frame almost never passes it);
* ``bus``: :func:`hilstack.bus.schemas.decode` for every message type (Zenoh payload -> message).

A *crash* is an exception other than the parser's documented error (the deframer and the
MAVLink decoder never raise: they count and skip; ``hilstack.bus.schemas.decode`` raises only
``MalformedMessage``) or a broken invariant (:class:`InvariantBroken`): counters that do
not add up, a receive buffer that grows without bound, a decoded message that does not
encode back to the same bytes.

The same harness functions run in two engines: hypothesis in the tests (a few hundred
examples per parser, ``tests/test_fuzz.py``) and atheris (libFuzzer, coverage-guided) in
`hil bench fuzz`, which runs each parser in its own process (libFuzzer owns the process
and exits at the first crash). A new parser gets a harness here and a line in
:data:`TARGETS`.

    hil bench fuzz --json --n 1000000
    python -m hilstack.tools.fuzz xbee -runs=100000     # one target, libFuzzer flags as usual
"""

from __future__ import annotations

import importlib
import os
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


class InvariantBroken(AssertionError):
    """A parser returned, but its state or output is inconsistent."""


def _check(ok: bool, why: str) -> None:
    if not ok:
        raise InvariantBroken(why)


# --------------------------------------------------------------------------- xbee
def fuzz_xbee(data: bytes) -> None:
    """The deframer over ``data[2:]``, read in three reads cut where ``data[0]`` and
    ``data[1]`` say (a frame or a corrupt run split over reads is the hard case)."""
    from hilstack.drivers.velociroach.link import MAX_FRAME_LEN, STALE_PARTIAL_S, XBeeDeframer

    if len(data) < 2:
        return
    body = data[2:]
    c1, c2 = sorted((data[0] * len(body) // 255, data[1] * len(body) // 255))
    d = XBeeDeframer()
    n_out = 0
    for part in (body[:c1], body[c1:c2], body[c2:]):
        out = d.feed(part, now_s=0.0)
        n_out += len(out)
        # an unfinished frame is all the deframer may keep
        _check(len(d._buf) < MAX_FRAME_LEN + 4, f"receive buffer holds {len(d._buf)} bytes")
        for f in out:
            _check(len(f.payload) <= MAX_FRAME_LEN, f"{len(f.payload)}-byte payload in one frame")
    n_out += len(d.feed(b"", now_s=2 * STALE_PARTIAL_S))  # the stream stops: a partial frame is stale
    _check(len(d._buf) == 0, f"{len(d._buf)} bytes left after the stream went stale")
    kinds = d.bad_checksum + d.truncated + d.garbage + d.bad_length
    _check(d.corrupt == kinds, f"corrupt={d.corrupt} but the kinds add up to {kinds}")
    _check(d.frames == n_out, f"frames={d.frames} but {n_out} frames were returned")
    _check(d.corrupt == 0 or d.last_error is not None, "corrupt input without a last_error")


def seeds_xbee() -> list[bytes]:
    from hilstack.drivers.velociroach.link import addr64, xbee_rx64, xbee_tx64

    a = addr64("0013A20040A1B2C3")
    out = []
    for i, f in enumerate(_mav_seed_frames()):
        rx, tx = xbee_rx64(a, f), xbee_tx64(a, f)
        out.append(bytes([40 * i % 256, 200]) + rx + tx)
        out.append(bytes([10, 128]) + b"noise" + rx[: len(rx) // 2] + tx)
    return out


# --------------------------------------------------------------------------- mavlink
def fix_mavlink_crc(frame: bytes) -> bytes:
    """``frame`` with a valid MAVLink v2 header checksum when its message id is known."""
    from pymavlink.generator.mavcrc import x25crc

    from hilstack.drivers.velociroach.mavlink import mav

    if len(frame) < 10:
        return frame
    n = frame[1]
    msgid = frame[7] | frame[8] << 8 | frame[9] << 16
    cls = mav.mavlink_map.get(msgid)
    if cls is None:
        return frame
    head = bytearray(b"\xfd" + frame[1:10 + n]).ljust(10 + n, b"\x00")
    crc = x25crc(bytes(head[1:]))
    crc.accumulate(bytes([cls.crc_extra]))
    return bytes(head) + crc.crc.to_bytes(2, "little") + frame[12 + n :]


def fuzz_mavlink(data: bytes) -> None:
    """``data[2:]`` split into frames of ``data[1] % 64 + 8`` bytes, decoded one by one;
    if ``data[0]`` is odd each frame first gets a valid CRC."""
    from hilstack.drivers.velociroach.mavlink import MavDecoder

    if len(data) < 3:
        return
    fix, size, body = data[0] & 1, data[1] % 64 + 8, data[2:]
    dec = MavDecoder()
    calls = 0
    for i in range(0, len(body), size):
        frame = body[i : i + size]
        if fix:
            frame = fix_mavlink_crc(frame)
        m = dec.decode(frame)
        calls += 1
        _check(m is None or isinstance(m.get_type(), str), f"decoded {m!r}")
        _check(dec.received + dec.corrupt == calls,
               f"received={dec.received} + corrupt={dec.corrupt} != {calls} frames decoded")
        _check(dec.dropped >= 0 and dec._unexplained_lost >= 0, "negative counter")
        _check(dec.corrupt == 0 or dec.last_error is not None, "corrupt frame without a last_error")


def _mav_seed_frames() -> list[bytes]:
    from hilstack.drivers.velociroach import mavlink as vm

    r = vm.MavEncoder(vm.ROBOT_SYSID, vm.ROBOT_COMPID)
    b = vm.MavEncoder(vm.BASE_SYSID, vm.BASE_COMPID)
    tel = {"t_fw_ms": 1, "gyro_rps": [0.1, 0.2, 0.3], "accel_mps2": [0.0, 0.0, 9.8], "crank_angle_rad": [1, 2],
           "crank_vel_rps": [3, 4], "bemf_v": [1, 1], "vbat_v": 3.9, "duty": [0.5, 0.5], "faults": 0}
    return [r.heartbeat(robot=True), r.telemetry(tel, last_cmd_seq=1, rx_good=2, rx_corrupt=0),
            r.pid_gains(1, 0.1, 0.2, 0.0, 0), r.status_text(4, 0, "watchdog"), b.leg_velocity(1, 1.0, -1.0, 15.0),
            b.pwm(2, 0.5, -0.5), b.heartbeat(), b.pid_set(3, 1.0, 2.0, 3.0), b.pid_get(4)]


def seeds_mavlink() -> list[bytes]:
    frames = _mav_seed_frames()
    return [bytes([1, (len(f) - 8) % 64]) + f for f in frames] + [b"\x00\x38" + b"".join(frames)]


# --------------------------------------------------------------------------- bus
def _bus_types() -> list[Any]:
    from hilstack.bus import schemas

    return [*schemas.ALL_TYPES, schemas.AnyMsg]


def fuzz_bus(data: bytes) -> None:
    """``data[1:]`` decoded as the message type ``data[0]`` picks (or as any message)."""
    from hilstack.bus import schemas

    if not data:
        return
    types = _bus_types()
    typ = types[data[0] % len(types)]
    try:
        m = schemas.decode(data[1:], typ)
    except schemas.MalformedMessage:
        return  # the documented error
    _check(isinstance(m, schemas.Msg), f"decoded a {type(m).__name__}")
    if isinstance(m, schemas.ModelUpdate):
        import numpy as np

        try:
            tensors = m.tensors()
        except schemas.MalformedMessage:
            pass  # the documented error
        else:
            _check(all(bool(np.isfinite(t).all()) for t in tensors.values()), "tensors() let NaN/inf through")
    raw = schemas.encode(m)
    # bytes, not ==: a NaN field is a valid float on the wire and never equals itself
    _check(schemas.encode(schemas.decode(raw, typ)) == raw, f"{type(m).__name__} does not round-trip")


def seeds_bus() -> list[bytes]:
    from hilstack.bus import schemas

    samples = [
        schemas.RobotState(robot="roach", t_s=1.0, state=[0.0, 1.5], action=[0.1, 0.2], health={"ok": True}),
        schemas.Command(robot="roach", action=[0.5, -0.5], state_seq=3),
        schemas.EStop(reason="operator"),
        schemas.Plan(robot="roach", actions=[[0.1, 0.2]], states=[[0.0], [1.0]]),
        schemas.Image(camera="c", t_s=0.0, width=2, height=1, data=b"\x00" * 6),
        schemas.SpecMsg(robot="roach", spec={"period_s": 0.1}),
        schemas.ModelUpdate.pack({"w": [[1.0, 2.0]]}, method="mb_de", info={"loss": 0.1}),
        schemas.TaskPosterior(method="mole", posterior=[0.25, 0.75], task=1, tasks_created=2),
        schemas.ResetEvent(robot="roach", phase="request", pose={"x": 0.0}),
        schemas.Ping(data=b"abc"),
    ]
    types = _bus_types()
    return [bytes([types.index(type(s))]) + schemas.encode(s) for s in samples] + [
        bytes([len(types) - 1]) + schemas.encode(samples[0])]


#: name -> (harness, seed inputs, packages atheris instruments for coverage)
TARGETS: dict[str, tuple[Callable[[bytes], None], Callable[[], list[bytes]], list[str]]] = {
    "xbee": (fuzz_xbee, seeds_xbee, ["hilstack.drivers.velociroach.link"]),
    "mavlink": (fuzz_mavlink, seeds_mavlink, ["hilstack.drivers.velociroach.mavlink", "pymavlink"]),
    "bus": (fuzz_bus, seeds_bus, ["hilstack.bus.schemas"]),
}
#: the config loaders and `hil`'s arguments (tools/fuzz_configs.py): generated documents
#: (the generator is instrumented too: its branches are the schema's fields and shapes, so
#: coverage guidance walks the schemas; pydantic's own validation is compiled code)
_CONFIG_TARGETS = {
    "robot_config": ("fuzz_robot_config", ["hilstack.tools.fuzz_configs", "hilstack.configs.schema"]),
    "rig_config": ("fuzz_rig_config", ["hilstack.tools.fuzz_configs", "hilstack.configs.schema"]),
    "task_config": ("fuzz_task_config", ["hilstack.tools.fuzz_configs", "hilstack.configs.schema"]),
    "reset_config": ("fuzz_reset_config", ["hilstack.tools.fuzz_configs", "hilstack.configs.schema",
                                           "hilstack.control.reset.config"]),
    "cli_args": ("fuzz_cli_args", ["hilstack.tools.fuzz_configs", "hilstack.tools.common"]),
}


def _config_target(fn: str) -> Callable[[bytes], None]:
    def run(data: bytes) -> None:
        from hilstack.tools import fuzz_configs

        getattr(fuzz_configs, fn)(data)

    run.__name__ = fn
    return run


def _config_seeds() -> list[bytes]:
    from hilstack.tools.fuzz_configs import seeds

    return seeds()


for _name, (_fn, _inst) in _CONFIG_TARGETS.items():
    TARGETS[_name] = (_config_target(_fn), _config_seeds, _inst)


def resolve(target: str) -> tuple[Callable[[bytes], None], Callable[[], list[bytes]], list[str]]:
    """A name of :data:`TARGETS`, or ``module:function`` (a harness taking bytes)."""
    if target in TARGETS:
        return TARGETS[target]
    mod, sep, fn = target.partition(":")
    if not sep:
        raise ValueError(f"unknown fuzz target {target!r}; known: {sorted(TARGETS)} or module:function")
    return getattr(importlib.import_module(mod), fn), lambda: [b""], [mod]


# --------------------------------------------------------------------------- runner
_DONE = re.compile(r"Done (\d+) runs in (\d+) second")
_EXECS = re.compile(r"#(\d+)\s+DONE\b.*?exec/s: (\d+)")


def _children_cpu_s() -> float:
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_target(target: str, n: int, *, seed: int = 1, max_len: int = 300,
               timeout_s: float = 3600.0) -> dict[str, Any]:
    """Fuzz one target with atheris for ``n`` inputs in a child process.

    Returns ``{"inputs", "crashes", "inputs_per_s", "seconds", "cpu_s", "inputs_per_cpu_s",
    "crash"}``; ``crash`` (the exception with its traceback, the child's last output lines
    and the input that crashed, in hex) only when one was found. libFuzzer
    stops at the first crash, so ``crashes`` is 0 or 1.
    """
    from hilstack.configs.extras import require

    require("atheris", "hil bench fuzz")
    _, seeds, _ = resolve(target)
    with tempfile.TemporaryDirectory(prefix="hil-fuzz-") as tmp:
        corpus = Path(tmp) / "corpus"
        corpus.mkdir()
        for i, s in enumerate(seeds()):
            (corpus / f"seed{i}").write_bytes(s)
        cmd = [sys.executable, "-m", "hilstack.tools.fuzz", target, f"-runs={n}", f"-seed={seed}", f"-max_len={max_len}",
               f"-artifact_prefix={tmp}/", "-print_final_stats=1", str(corpus)]
        if target in _CONFIG_TARGETS:  # a generated document needs its choices from the start: full-length inputs
            cmd.insert(-1, "-len_control=0")
        t0, cpu0 = time.monotonic(), _children_cpu_s()
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout_s, env=env)
        seconds, cpu_s = time.monotonic() - t0, _children_cpu_s() - cpu0
        log = r.stdout + r.stderr
        done = _DONE.search(log)
        execs = _EXECS.search(log)
        inputs = int(done.group(1)) if done else (int(execs.group(1)) if execs else None)
        out: dict[str, Any] = {
            "inputs": inputs,
            "crashes": 0 if r.returncode == 0 and done else 1,
            "inputs_per_s": round(inputs / seconds) if inputs else None,
            "seconds": round(seconds, 1),
            # CPU time of the fuzzing process: on a shared machine the wall clock says little
            "cpu_s": round(cpu_s, 1),
            "inputs_per_cpu_s": round(inputs / cpu_s) if inputs and cpu_s > 0 else None,
        }
        if out["crashes"]:
            saved = sorted(Path(tmp).glob("crash-*"))
            lines = [ln.rstrip() for ln in log.splitlines()]
            marks = [i for i, ln in enumerate(lines) if ln.strip() == "=== Uncaught Python exception: ==="]
            exc: list[str] = []
            if marks:  # atheris' report of the crash
                for ln in lines[marks[0] + 1 :]:
                    if not ln.strip():
                        break
                    exc.append(ln)
            out["crash"] = {"exit_code": r.returncode, "exception": exc, "log_tail": lines[-25:],
                            "input_hex": saved[0].read_bytes()[:512].hex() if saved else None}
    return out


def run_bench_fuzz(n: int = 1_000_000, targets: list[str] | None = None, seed: int = 1) -> dict[str, Any]:
    """Every target for ``n`` inputs; ``crashes`` is the total over targets."""
    res = {t: run_target(t, n, seed=seed) for t in (targets or list(TARGETS))}
    return {"n": n, "engine": "atheris", "targets": res, "crashes": sum(r["crashes"] for r in res.values())}


def main(argv: list[str] | None = None) -> None:
    """``python -m hilstack.tools.fuzz TARGET [libFuzzer flags] [corpus dir]`` under atheris."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m hilstack.tools.fuzz", description=__doc__.split("\n")[0],
                                 epilog="Everything after TARGET goes to libFuzzer (e.g. -runs=100000 CORPUS_DIR).")
    ap.add_argument("target", help=f"one of {sorted(TARGETS)} or module:function")
    ap.add_argument("libfuzzer", nargs=argparse.REMAINDER, help="libFuzzer flags and corpus directories")
    a = ap.parse_args(argv)
    _atheris_main([a.target, *a.libfuzzer])


def _atheris_main(argv: list[str]) -> None:
    import atheris

    target = argv[0]
    include = TARGETS[target][2] if target in TARGETS else [target.partition(":")[0]]
    with atheris.instrument_imports(include=include):
        for mod in include:
            importlib.import_module(mod)
    harness, _, _ = resolve(target)
    if target == "mavlink":
        # the dialect module is generated and loaded from a cache file, past the import
        # hook: instrument its decoding code by hand (instrument_all would be 3x slower)
        import inspect

        from hilstack.drivers.velociroach.mavlink import mav

        for cls in (mav.MAVLink, mav.MAVLink_message, mav.MAVLink_header):
            for _, fn in inspect.getmembers(cls, inspect.isfunction):
                if fn.__module__ == mav.__name__:
                    atheris.instrument_func(fn)
    atheris.Setup([sys.argv[0], *argv[1:]], harness)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
