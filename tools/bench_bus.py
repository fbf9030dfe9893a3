"""Bus latency benchmark: ping-pong through hilstack's node layer vs raw zenoh-python.

Two processes on loopback. The pong process echoes; the ping process measures the
round trip. Both stacks run in the same invocation with the same payload sizes, so
``ratio_p50`` and ``ratio_p99`` (ours / raw) compare like with like on the same machine
and load. A bare TCP ping-pong over loopback between two Python processes (``tcp``, same
sizes) is the floor: ``raw_over_tcp_p50`` says how far raw Zenoh is above what the
machine does with the least possible work.

Two reference stacks say where the node layer's time goes (informative, not the goal's
peer): ``ring`` is raw zenoh-python with the channel a node's subscription uses
(``RingChannel(8)``, blocking ``recv()``) instead of the default FIFO; ``ring_typed`` is
``ring`` plus what any typed bus does per message (msgspec encode of a :class:`Ping`,
``to_bytes()`` and decode at both ends), without the node layer.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time

import numpy as np
import zenoh

from hilstack.bus.node import Node
from hilstack.bus.ports import free_port
from hilstack.bus.schemas import Ping, decoder, encode
from hilstack.bus.session import open_session
from hilstack.configs.schema import BusConfig

PING, PONG = "hil/bench/ping", "hil/bench/pong"




def _recv_exact(conn: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = conn.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("bench: tcp peer closed")
        buf += chunk
    return bytes(buf)


def _tcp_addr(endpoint: str) -> tuple[str, int]:
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    return host, int(port)


#: ``--pin``: the CPU the pong processes run on (the environment tells them; the ping side pins itself)
PIN_ENV = "HIL_BENCH_PONG_CPU"


def _pin_cpus() -> tuple[int, int]:
    """Two CPUs for ``--pin``: the ping process on the first, every pong process on the second."""
    if not hasattr(os, "sched_setaffinity"):
        raise ValueError("bench bus: --pin needs os.sched_setaffinity (Linux)")
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        raise ValueError(f"bench bus: --pin needs 2 CPUs, this process may use {len(cpus)}")
    return cpus[0], cpus[1]


def _pong(mode: str, endpoint: str) -> None:
    if os.environ.get(PIN_ENV):
        os.sched_setaffinity(0, {int(os.environ[PIN_ENV])})  # before Zenoh starts its threads
    if mode == "tcp":
        # length-prefixed echo on a plain socket: the floor of a loopback round trip
        with socket.create_server(_tcp_addr(endpoint)) as srv:
            print("ready", flush=True)
            conn, _ = srv.accept()
            with conn:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                while True:
                    n = int.from_bytes(_recv_exact(conn, 4), "little")
                    if n == 0:
                        break
                    conn.sendall(n.to_bytes(4, "little") + _recv_exact(conn, n))
        return
    bus = BusConfig(endpoint=endpoint) if mode != "router" else BusConfig(router=endpoint)
    if mode == "node":
        node = Node("pong", "bench", bus)
        sub = node.subscribe(PING, Ping)
        pub = node.publisher(PONG, Ping)
        print("ready", flush=True)
        while True:
            m = sub.wait(5.0)
            if m is None:
                continue
            if m.data == b"quit":
                break
            pub.put(m)
        node.close()
    else:
        s = open_session(bus)
        sub = s.declare_subscriber(PING, *((zenoh.handlers.RingChannel(8),) if mode.startswith("ring") else ()))
        pub = s.declare_publisher(PONG, express=True)
        print("ready", flush=True)
        if mode == "ring_typed":
            decode = decoder(Ping)
            while True:
                m = decode(sub.recv().payload.to_bytes())
                if m.data == b"quit":
                    break
                pub.put(encode(m))
        while mode != "ring_typed":
            sample = sub.recv()
            payload = sample.payload.to_bytes()
            if payload == b"quit":
                break
            pub.put(payload)
        s.close()


class _Client:
    """The ping side of one stack: ``round_trip()`` sends one message and waits for its echo."""

    def __init__(self, mode: str, endpoint: str, size: int):
        self.mode = mode
        if mode == "tcp":
            deadline = time.monotonic() + 10
            while True:
                try:
                    self._conn = socket.create_connection(_tcp_addr(endpoint), timeout=10)
                    break
                except ConnectionRefusedError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.05)
            self._conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            frame = size.to_bytes(4, "little") + b"x" * size

            def rt() -> None:
                self._conn.sendall(frame)
                _recv_exact(self._conn, 4 + size)
        elif mode == "node":
            self._node = Node("ping", "bench", BusConfig(endpoint=endpoint), handle_signals=False)
            sub = self._node.subscribe(PONG, Ping)
            pub = self._pub = self._node.publisher(PING, Ping)
            msg = Ping(data=b"x" * size)
            _wait_link(lambda: pub.put(msg), lambda: sub.wait(0.05))

            def rt() -> None:
                pub.put(msg)
                # a finite timeout, as the nodes wait (the timed path is the one callers use)
                if sub.wait(5.0) is None:
                    raise RuntimeError("bench: node echo lost")
        else:
            bus = BusConfig(endpoint=endpoint) if mode != "router" else BusConfig(router=endpoint)
            self._s = open_session(bus)
            rsub = self._s.declare_subscriber(PONG, *((zenoh.handlers.RingChannel(8),) if mode.startswith("ring") else ()))
            rpub = self._rpub = self._s.declare_publisher(PING, express=True)
            payload = b"x" * size
            msg = Ping(data=payload)
            if mode == "ring_typed":
                payload = encode(msg)  # the probes below: a message the pong can decode
            _wait_link(lambda: rpub.put(payload), lambda: rsub.try_recv() or (time.sleep(0.05) or rsub.try_recv()))

            if mode == "ring_typed":
                decode = decoder(Ping)

                def rt() -> None:
                    rpub.put(encode(msg))
                    decode(rsub.recv().payload.to_bytes())
            else:

                def rt() -> None:
                    rpub.put(payload)
                    rsub.recv()
        self.round_trip = rt

    def close(self) -> None:
        if self.mode == "tcp":
            self._conn.sendall((0).to_bytes(4, "little"))
            self._conn.close()
        elif self.mode == "node":
            self._pub.put(Ping(data=b"quit"))
            time.sleep(0.05)
            self._node.close()
        else:
            self._rpub.put(b"quit" if self.mode != "ring_typed" else encode(Ping(data=b"quit")))
            time.sleep(0.05)
            self._s.close()


def _wait_link(send, recv, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        send()
        if recv():
            # drain echoes of the probes
            t = time.monotonic() + 0.2
            while time.monotonic() < t:
                recv()
            return
    raise RuntimeError("bench: no echo from the pong process (is the port free?)")


MODES = ("tcp", "raw", "ring", "ring_typed", "node")


def _router(endpoint: str) -> None:
    """A Zenoh router with the project's config (bus/session.py: router_config), as `hil router` runs it."""
    import signal
    import threading

    import zenoh

    from hilstack.bus.session import router_config

    s = zenoh.open(router_config(BusConfig(router=endpoint), "bench", []))
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print("ready", flush=True)
    stop.wait()
    s.close()


def run_bench_bus(n: int = 2000, sizes: tuple[int, ...] = (64, 4096), warmup: int = 200, block: int = 100,
                  via_router: bool = False, pin: bool = False) -> dict:
    """Per size, the stacks run at once (one pong process each) and take turns in blocks of
    ``block`` round trips, so a change of load on the machine hits each alike. ``via_router``
    adds ``router``: raw Zenoh with both ends clients of a router process on 127.0.0.2 (the
    extra hop of a rig spread over hosts, `hil router`), beside ``raw`` (the direct peer hop).

    ``pin``: the ping side on one CPU and every pong process on another (Linux). Unpinned, each
    stack's pair of processes lands on the same core or on two, by chance, and a round trip's
    p50 differs about 2x between the two (45 vs 100 us on the 2-core development machine), so
    one run's ratio said more about placement than about the stacks."""
    out: dict = {"n": n, "pinned": pin}
    child_env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if pin:
        ping_cpu, pong_cpu = _pin_cpus()
        before = os.sched_getaffinity(0)
        os.sched_setaffinity(0, {ping_cpu})  # this thread; the stacks' Zenoh threads inherit it
        child_env[PIN_ENV] = str(pong_cpu)
        try:
            return _run(out, n, sizes, warmup, block, via_router, child_env)
        finally:
            os.sched_setaffinity(0, before)
    return _run(out, n, sizes, warmup, block, via_router, child_env)


def _run(out: dict, n: int, sizes: tuple[int, ...], warmup: int, block: int, via_router: bool,
         child_env: dict) -> dict:
    modes = MODES + (("router",) if via_router else ())
    for size in sizes:
        procs, clients = [], {}
        try:
            for mode in modes:
                ep = f"tcp/127.0.0.1:{free_port()}"
                if mode == "router":
                    ep = f"tcp/127.0.0.2:{free_port('127.0.0.2')}"
                    rp = subprocess.Popen([sys.executable, "-m", "hilstack.tools.bench_bus", "router", ep],
                                          stdout=subprocess.PIPE, text=True)
                    procs.append(rp)
                    if rp.stdout.readline().strip() != "ready":
                        raise RuntimeError("bench: the router process did not start")
                proc = subprocess.Popen(
                    [sys.executable, "-m", "hilstack.tools.bench_bus", "pong", mode, ep],
                    stdout=subprocess.PIPE,
                    text=True,
                    env=child_env,
                )
                procs.append(proc)
                if proc.stdout.readline().strip() != "ready":
                    raise RuntimeError(f"bench: the {mode} pong process did not start")
                clients[mode] = _Client(mode, ep, size)
            lat = {m: np.empty(n) for m in modes}
            for c in clients.values():
                for _ in range(warmup):
                    c.round_trip()
            for start in range(0, n, block):
                for m, c in clients.items():
                    rt, arr = c.round_trip, lat[m]
                    for i in range(start, min(n, start + block)):
                        t = time.perf_counter()
                        rt()
                        arr[i] = time.perf_counter() - t
        finally:
            for c in clients.values():
                try:
                    c.close()
                except Exception:
                    pass
            for proc in procs[::-1]:
                try:
                    if proc.args[3] == "router":
                        proc.terminate()
                    proc.wait(5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        row: dict = {
            m: {"p50_us": float(np.percentile(lat[m] * 1e6, 50)), "p99_us": float(np.percentile(lat[m] * 1e6, 99))}
            for m in modes
        }
        for q in ("p50", "p99"):
            row[f"ratio_{q}"] = row["node"][f"{q}_us"] / row["raw"][f"{q}_us"]
        row["raw_over_tcp_p50"] = row["raw"]["p50_us"] / row["tcp"]["p50_us"]
        # where the node's time goes: its channel (ring / raw), typed messages (ring_typed / ring),
        # the node layer itself (node / ring_typed)
        for a, b in (("ring", "raw"), ("ring_typed", "ring"), ("node", "ring_typed")):
            row[f"{a}_over_{b}_p50"] = row[a]["p50_us"] / row[b]["p50_us"]
        if via_router:
            row["router_over_raw_p50"] = row["router"]["p50_us"] / row["raw"]["p50_us"]
        out[f"{size}B"] = row
    for q in ("ratio_p50", "ratio_p99"):
        out[q] = max(out[f"{s}B"][q] for s in sizes)
    out["loadavg_1min"] = os.getloadavg()[0]
    return out


def main(argv: list[str] | None = None) -> None:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m hilstack.tools.bench_bus", description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=2000, help="round trips per payload size (default 2000)")
    ap.add_argument("--pin", action="store_true", help="ping on one CPU, the pong processes on another (Linux)")
    sub = ap.add_subparsers(dest="cmd")
    pong = sub.add_parser("pong", help="the echo process the benchmark starts itself")
    pong.add_argument("mode", choices=(*MODES, "router"))
    rt = sub.add_parser("router", help="the router process of --via-router")
    rt.add_argument("endpoint", help="tcp/HOST:PORT")
    pong.add_argument("endpoint", help="tcp/HOST:PORT")
    a = ap.parse_args(argv)
    if a.cmd == "pong":
        _pong(a.mode, a.endpoint)
    elif a.cmd == "router":
        _router(a.endpoint)
    else:
        print(json.dumps(run_bench_bus(n=a.n, pin=a.pin)))


if __name__ == "__main__":
    main()
