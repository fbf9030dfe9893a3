"""State → adapted model at the MPC: the delay of online adaptation on a realtime rig.

One run on a wall-clock rig (default ``roach_emulated``: the real radio driver over a pty to
the firmware emulator, 10 Hz; a lockstep sim rig such as ``roach_sim`` is run paced on the
wall clock instead):

* ``hil up RIG`` (driver node + emulator) and, in this process, a controller commanding the
  robot at the control rate (the MBRL loop's safe random policy: cheap, so the delay is the
  adaptation's, not a planner's);
* per payload, ``hil adapt RIG`` in its own process on a 3 x 512 model (the thesis' GrBAL
  size), M = 16, and in this process the MPC's receiving end (:class:`ModelSwap`: decode,
  validate, build the dynamics). The delay is ``time.time_ns()`` when the new dynamics are
  built minus the stamp of the newest state the update used (``RobotState.stamp_s``, the
  driver node's publish time; one host, one clock). The MPC plans with it from its next plan;
* payloads: ``full`` (GrBAL adapting and sending every parameter, ~2.2 MB), ``last_layer``
  (GrBAL adapting and sending only the output layer) and ``context`` (ReBAL's GRU state);
* the peer: raw zenoh-python put/get ping-pong of the same byte counts, and the node layer's
  (``hil bench bus``, same run); ``ratio_p50`` = our delay p50 / raw one-way p50 (half the
  round trip).

``choice``: the largest payload of GrBAL (full, else last layer) whose p99 delay fits in one
control period. Models are untrained (random θ*, ψ = 1e-3): the compute is the same.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from hilstack.bus import keys
from hilstack.bus.node import alive_nodes
from hilstack.bus.ports import free_port
from hilstack.bus.schemas import ModelUpdate
from hilstack.configs.schema import load_rig, rig_robot_config
from hilstack.control.controller_node import ControllerNode
from hilstack.control.policies import SafeRandomPolicy
from hilstack.drivers.registry import make_driver
from hilstack.learning.adaptation import load_adapter
from hilstack.learning.adaptation.grbal import GrbalAdapter
from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.adaptation.node import ModelSwap, last_layer
from hilstack.learning.adaptation.rebal import ContextEncoder, RebalAdapter
from hilstack.tools.bench_bus import run_bench_bus

PAYLOADS = ("full", "last_layer", "context")
#: channels of a planar robot (body-frame model, the safe random policy's arena)
PLANAR = ("x", "y", "vx", "vy", "cos_yaw", "sin_yaw")


def write_checkpoints(out: Path, state_names: list[str], action_dim: int, hidden: tuple[int, ...],
                      window: int, context_dim: int) -> dict[str, Path]:
    """One checkpoint per payload (untrained; same sizes as trained ones)."""
    torch.manual_seed(0)
    planar = set(PLANAR) <= set(state_names)
    model = AdaptiveMLP(state_names, action_dim, hidden=hidden, body_frame=planar)
    psi = {k: torch.full_like(v, 1e-3) for k, v in model.params().items()}
    full = GrbalAdapter(model, psi, window=window)
    paths = {"full": out / "grbal_full.pt", "last_layer": out / "grbal_last_layer.pt", "context": out / "rebal.pt"}
    full.save(paths["full"])
    GrbalAdapter(model, psi, window=window, adapt_params=last_layer(full)).save(paths["last_layer"])
    cmodel = AdaptiveMLP(state_names, action_dim, hidden=hidden, body_frame=planar, context_dim=context_dim)
    RebalAdapter(cmodel, ContextEncoder(cmodel, context_dim), window=window).save(paths["context"])
    return paths


def _cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "hilstack.tools.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _stop(p: subprocess.Popen, timeout_s: float = 10.0) -> tuple[str, str]:
    if p.poll() is None:
        p.terminate()
    try:
        return p.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        p.kill()
        return p.communicate()


def _pct(x: list[float] | np.ndarray) -> dict[str, float]:
    a = np.asarray(x, dtype=float)
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99))} if a.size else {}


def measure_payload(ctl: ControllerNode, rig: str, rig_file: str, ep: str, ck: Path, updates: int,
                    timeout_s: float) -> dict[str, Any]:
    """Run ``hil adapt`` on ``ck`` and receive ``updates`` updates the way the MPC does."""
    adapter = load_adapter(ck)
    sub = ctl.subscribe(keys.model_update(rig), ModelUpdate)
    swap = ModelSwap(adapter, sub)
    sizes: list[int] = []
    node = _cli("adapt", rig, "--checkpoint", str(ck), "--json", "--endpoint", ep)
    try:
        deadline = time.monotonic() + timeout_s
        while "adaptation" not in alive_nodes(ctl.session, rig, timeout_s=0.2):
            if node.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"bench: hil adapt did not come up: {_stop(node)[1].strip()[-500:]}")
            time.sleep(0.1)
        sub.poll()  # nothing from before the measurement
        while swap.stats.applied + swap.stats.rejected < updates:
            if time.monotonic() > deadline:
                raise RuntimeError(f"bench: {swap.stats.applied} of {updates} updates within {timeout_s} s")
            if node.poll() is not None:
                raise RuntimeError(f"bench: hil adapt exited: {_stop(node)[1].strip()[-500:]}")
            if sub.wait_queued(1.0) and swap() is not None:
                sizes.append(len(swap.current.data))
    finally:
        out, err = _stop(node)
        sub.close()
    try:
        node_stats = json.loads(out.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        node_stats = {"error": err.strip()[-500:]}
    delay = list(swap.stats.delay_ms)
    return {
        "method": adapter.name,
        "bytes": int(np.median(sizes)) if sizes else 0,
        "delay_ms": _pct(delay),
        "received": swap.stats.applied,
        "rejected": swap.stats.rejected,
        # the latest-value queue keeps only the newest: updates the receiver never saw
        "superseded": sub.dropped,
        "node_update_ms": {"p50": node_stats.get("update_ms_p50"), "p99": node_stats.get("update_ms_p99")},
        "node_update_cpu_ms": {"p50": node_stats.get("update_cpu_ms_p50"), "p99": node_stats.get("update_cpu_ms_p99")},
        "node": {k: node_stats.get(k) for k in ("states", "transitions", "updates", "skipped_gap", "skipped_not_ok",
                                                "skipped_stopped", "window_clears")},
    }


def run_bench_adaptation(rig: str = "roach_emulated", updates: int = 100, hidden: tuple[int, ...] = (512, 512, 512),
                         window: int = 16, context_dim: int = 32, payloads: tuple[str, ...] = PAYLOADS,
                         peer_n: int = 300, timeout_s: float = 180.0) -> dict[str, Any]:
    cfg = load_rig(rig)
    tmpdir = tempfile.TemporaryDirectory()
    if cfg.pace != "realtime":
        if any(r.backend != "sim" for r in cfg.robots.values()):
            raise ValueError(f"rig {rig} runs in {cfg.pace} pace: the delay needs a wall-clock rig")
        # a lockstep sim rig, paced on the wall clock instead (what a realtime sim rig is)
        doc = yaml.safe_load(Path(cfg.source).read_text())
        doc["pace"] = "realtime"
        rig = str(Path(tmpdir.name) / "rig_realtime.yaml")
        Path(rig).write_text(yaml.safe_dump(doc))
        cfg = load_rig(rig)
    robot = next(iter(cfg.robots))
    spec = make_driver(rig_robot_config(cfg, robot)).spec
    period_ms = spec.period_s * 1e3
    ep = f"tcp/127.0.0.1:{free_port()}"
    from hilstack.tools.common import provision_credentials, with_endpoint

    bus = with_endpoint(cfg.bus, ep)  # the rig's own bus (its access control) on a private port
    provision_credentials(cfg.name, bus, cfg)
    out: dict[str, Any] = {"rig": cfg.name, "pace": cfg.pace, "backend": cfg.robots[robot].backend, "period_ms": period_ms, "updates": updates, "hidden": list(hidden),
                           "window": window, "cpus": os.cpu_count(), "load_avg_1min": os.getloadavg()[0]}
    with tmpdir as tmp:
        cks = write_checkpoints(Path(tmp), list(spec.state.names), len(spec.action.names), hidden, window,
                                context_dim)
        up = _cli("up", str(cfg.source or rig), "--endpoint", ep)
        ctl = None
        try:
            ctl = ControllerNode(cfg.name, robot, bus, name="bench-controller", handle_signals=False,
                                 state_timeout_s=30)
            try:
                ctl.wait_ready(120)
            except TimeoutError:
                raise RuntimeError(f"bench: rig {rig} did not come up: {_stop(up)[1].strip()[-500:]}") from None
            A = len(spec.action.names)
            if set(PLANAR) <= set(spec.state.names):
                policy = SafeRandomPolicy(spec.state.names, A, hold_steps=10, forward_fraction=0.8 if A == 2 else 0,
                                          seed=0)
            else:  # no heading to keep it in an arena: small random commands
                rng = np.random.default_rng(0)
                policy = lambda s: rng.uniform(-0.3, 0.3, A)  # noqa: E731
            drive = threading.Thread(target=ctl.run_realtime, args=(policy, 10**9), daemon=True, name="drive")
            drive.start()
            for name in payloads:
                if up.poll() is not None:
                    raise RuntimeError(f"bench: the rig's driver node exited: {_stop(up)[1].strip()[-500:]}")
                try:
                    out[name] = measure_payload(ctl, cfg.name, str(cfg.source or rig), ep, cks[name], updates,
                                                timeout_s)
                except RuntimeError as e:
                    rig_log = _stop(up)[1].strip().splitlines()[-3:] if up.poll() is not None else ["(still running)"]
                    raise RuntimeError(f"{e} [payload {name}; driver node: {' | '.join(rig_log)}]") from None
                print(f"bench adaptation: {name}: {out[name]['delay_ms']}", file=sys.stderr, flush=True)
            ctl.stop_event.set()
            drive.join(5)
        finally:
            if ctl is not None:
                ctl.close()
            _stop(up)
    sizes = tuple(sorted({max(1, out[n]["bytes"]) for n in payloads}))
    peer = run_bench_bus(n=peer_n, sizes=sizes, warmup=20)
    for name in payloads:
        row = peer[f"{max(1, out[name]['bytes'])}B"]
        raw_oneway_ms = row["raw"]["p50_us"] / 2e3
        out[name]["raw_oneway_ms_p50"] = raw_oneway_ms
        out[name]["node_oneway_ms_p50"] = row["node"]["p50_us"] / 2e3
        d = out[name]["delay_ms"]
        out[name]["ratio_p50"] = d["p50"] / raw_oneway_ms if d else None
        # what is not the node's own compute: transport, decoding, validation, building the dynamics
        nu = out[name]["node_update_ms"]["p50"]
        out[name]["delay_minus_node_update_ms_p50"] = d["p50"] - nu if d and nu is not None else None
        out[name]["within_period"] = bool(d) and d["p99"] < period_ms
    grbal = [n for n in ("full", "last_layer") if n in payloads and out[n]["within_period"]]
    out["choice"] = grbal[0] if grbal else None
    if not grbal:
        out["note"] = (f"no GrBAL payload's p99 fit in {period_ms:.0f} ms at 1-min load {out['load_avg_1min']:.1f} on "
                       f"{out['cpus']} CPUs: compare node_update_ms (wall) with node_update_cpu_ms (CPU) to see how "
                       "much of it is waiting for a CPU")
    return out


def main(argv: list[str] | None = None) -> None:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m hilstack.tools.bench_adaptation", description=__doc__.split("\n")[0])
    ap.add_argument("updates", nargs="?", type=int, default=100, help="model updates to time (default 100)")
    print(json.dumps(run_bench_adaptation(updates=ap.parse_args(argv).updates), indent=2))


if __name__ == "__main__":
    main()
