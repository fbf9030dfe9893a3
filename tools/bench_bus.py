"""Bus latency benchmark: ping-pong through hilstack's node layer vs raw zenoh-python.

Two processes on loopback. The pong process echoes; the ping process measures the
round trip. Both stacks run in the same invocation with the same payload sizes, so
``ratio_p50`` (ours / raw) compares like with like on the same machine and load.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time

import numpy as np

from hilstack.bus.node import Node
from hilstack.bus.schemas import Ping
from hilstack.bus.session import open_session
from hilstack.configs.schema import BusConfig

PING, PONG = "hil/bench/ping", "hil/bench/pong"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _pong(mode: str, endpoint: str) -> None:
    bus = BusConfig(endpoint=endpoint)
    if mode == "node":
        node = Node("pong", "bench", bus)
        sub = node.subscribe(PING, Ping)
        pub = node.publisher(PONG, Ping)
        print("ready", flush=True)
        while True:
            m = sub.wait(None)
            if m.data == b"quit":
                break
            pub.put(m)
        node.close()
    else:
        s = open_session(bus)
        sub = s.declare_subscriber(PING)
        pub = s.declare_publisher(PONG, express=True)
        print("ready", flush=True)
        while True:
            sample = sub.recv()
            payload = sample.payload.to_bytes()
            if payload == b"quit":
                break
            pub.put(payload)
        s.close()


def _ping(mode: str, endpoint: str, size: int, n: int, warmup: int) -> np.ndarray:
    bus = BusConfig(endpoint=endpoint)
    lat = np.empty(n)
    if mode == "node":
        node = Node("ping", "bench", bus, handle_signals=False)
        sub = node.subscribe(PONG, Ping)
        pub = node.publisher(PING, Ping)
        msg = Ping(data=b"x" * size)
        _wait_link(lambda: pub.put(msg), lambda: sub.wait(0.05))
        for i in range(warmup + n):
            t = time.perf_counter()
            pub.put(msg)
            got = sub.wait(None)
            if i >= warmup:
                lat[i - warmup] = time.perf_counter() - t
            assert got is not None
        pub.put(Ping(data=b"quit"))
        time.sleep(0.05)
        node.close()
    else:
        s = open_session(bus)
        sub = s.declare_subscriber(PONG)
        pub = s.declare_publisher(PING, express=True)
        payload = b"x" * size
        _wait_link(lambda: pub.put(payload), lambda: sub.try_recv() or (time.sleep(0.05) or sub.try_recv()))
        for i in range(warmup + n):
            t = time.perf_counter()
            pub.put(payload)
            sub.recv()
            if i >= warmup:
                lat[i - warmup] = time.perf_counter() - t
        pub.put(b"quit")
        time.sleep(0.05)
        s.close()
    return lat


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


def run_bench_bus(n: int = 2000, sizes: tuple[int, ...] = (64, 4096), warmup: int = 200) -> dict:
    out: dict = {"n": n}
    for size in sizes:
        row = {}
        for mode in ("raw", "node"):
            ep = f"tcp/127.0.0.1:{free_port()}"
            proc = subprocess.Popen(
                [sys.executable, "-m", "hilstack.tools.bench_bus", "pong", mode, ep],
                stdout=subprocess.PIPE,
                text=True,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
            try:
                assert proc.stdout.readline().strip() == "ready"
                lat = _ping(mode, ep, size, n, warmup) * 1e6
            finally:
                try:
                    proc.wait(5)
                except subprocess.TimeoutExpired:
                    proc.kill()
            row[mode] = {"p50_us": float(np.percentile(lat, 50)), "p99_us": float(np.percentile(lat, 99))}
        row["ratio_p50"] = row["node"]["p50_us"] / row["raw"]["p50_us"]
        out[f"{size}B"] = row
    out["ratio_p50"] = max(out[f"{s}B"]["ratio_p50"] for s in sizes)
    return out


if __name__ == "__main__":
    if len(sys.argv) >= 4 and sys.argv[1] == "pong":
        _pong(sys.argv[2], sys.argv[3])
    else:
        print(json.dumps(run_bench_bus()))
