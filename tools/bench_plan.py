"""Planning-latency benchmark: our planners vs pytorch-mppi's MPPI on the same model.

Workloads (the two systems of the research):

* **A** VelociRoACH: state 24, action 2, one model, 500 samples, horizon 4, random shooting,
  path-following cost on a figure-8.
* **B** Shadow Hand / PDDM: state 40, action 24, ensemble of 3, 700 samples, horizon 7, PDDM
  (γ=20, β=0.7), quadratic goal cost on the first 6 state channels (two ball positions).

Both use a 2x500 ReLU MLP (:class:`learning.dynamics.EnsembleDynamics`, random init).
The peer is ``pytorch_mppi.MPPI`` with the same model object, the same cost (as its
``terminal_state_cost``, which receives the whole predicted trajectory), the same samples,
horizon and noise σ, ``lambda_ = 1/γ`` (which gives the same e^{γ(R - max R)} weights),
and for the ensemble ``rollout_samples = E`` with each rollout sample routed to one member.
Both run under ``torch.inference_mode`` and get the state as numpy and return numpy, so
both use the model's fused inference path; the difference measured is the planner's.

``run_bench_plan`` returns latency percentiles in milliseconds over ``calls`` planning calls
after ``warmup`` calls. Use it through ``hil bench plan --json`` or
``python -m tools.bench_plan``.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable

import numpy as np
import torch

from control.costs import PathCost
from control.paths import make_path
from control.planners import PDDM, RandomShooting
from learning.dynamics import EnsembleDynamics, cpu_bf16_support

__all__ = ["run_bench_plan", "WORKLOADS"]

ROACH_STATE_NAMES = [
    "x", "y", "z", "vx", "vy", "vz", "cos_roll", "sin_roll", "cos_pitch", "sin_pitch",
    "cos_yaw", "sin_yaw", "wx", "wy", "wz", "cos_left_crank", "sin_left_crank",
    "cos_right_crank", "sin_right_crank", "left_crank_vel", "right_crank_vel",
    "left_bemf", "right_bemf", "vbat",
]  # fmt: skip

WORKLOADS = {
    "A": {"state_dim": 24, "action_dim": 2, "ensemble": 1, "samples": 500, "horizon": 4, "planner": "random_shooting"},
    "B": {"state_dim": 40, "action_dim": 24, "ensemble": 3, "samples": 700, "horizon": 7, "planner": "pddm"},
}
GAMMA, BETA, SIGMA = 20.0, 0.7, 0.3


def _percentiles(times_s: list[float]) -> dict[str, float]:
    ms = np.asarray(times_s) * 1e3
    return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99))}


def _time_calls(fn: Callable[[], object], calls: int, warmup: int) -> list[float]:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(calls):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def _cost_for(name: str, S: int):
    """Trajectory cost ``(states [E,N,H+1,S], actions [N,H,A]) -> [E,N]`` of a workload."""
    if name == "A":
        return PathCost(make_path("figure8"), ROACH_STATE_NAMES)
    goal = torch.linspace(-0.1, 0.1, 6)

    def hand_cost(states, actions):
        # ball positions (first 6 channels) to the goal, plus a small action magnitude term
        pos = states[..., 1:, :6]
        return ((pos - goal) ** 2).sum(dim=(-1, -2)) + 1e-3 * (actions**2).sum(dim=(-1, -2))

    return hand_cost


def _make_planner(w: dict):
    kw = dict(horizon=w["horizon"], samples=w["samples"], action_dim=w["action_dim"], seed=0)
    if w["planner"] == "random_shooting":
        return RandomShooting(-1.0, 1.0, **kw)
    return PDDM(-1.0, 1.0, gamma=GAMMA, beta=BETA, sigma=SIGMA, **kw)


def _make_peer(model: EnsembleDynamics, cost, w: dict, s0: torch.Tensor, predict):
    try:
        from pytorch_mppi import MPPI  # noqa: PLC0415 - optional peer
    except ImportError:
        raise ModuleNotFoundError("hil bench plan compares with pytorch-mppi: pip install 'hilstack[bench]'") from None

    E, S, A = w["ensemble"], w["state_dim"], w["action_dim"]
    K = w["samples"]

    def dynamics(state, action):  # [E*K, S] (rollout sample m -> member m), [E*K, A]
        if E == 1:
            return predict(state, action)[0]
        return predict(state.view(E, K, S), action.view(E, K, A)).reshape(E * K, S)

    def running_cost(state, action):
        return torch.zeros(state.shape[0])

    def terminal(states, actions):  # [M, K, T, S], [M, K, T, A] -> [M, K]
        full = torch.cat([s0.expand(states.shape[0], K, 1, S), states], dim=2)
        return cost(full, actions[0])

    return MPPI(
        dynamics,
        running_cost,
        S,
        noise_sigma=(SIGMA**2) * torch.eye(A),
        num_samples=K,
        horizon=w["horizon"],
        lambda_=1.0 / GAMMA,
        u_min=-torch.ones(A),
        u_max=torch.ones(A),
        rollout_samples=E,
        terminal_state_cost=terminal,
    )


def _time_interleaved(fns: dict[str, Callable[[], object]], calls: int, warmup: int) -> dict[str, list[float]]:
    """Time several callables call by call in turn, so that load from other processes on a
    shared machine hits all of them alike instead of whichever happened to run at the time."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    out: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(calls):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            out[k].append(time.perf_counter() - t0)
    return out


def bench_workload(name: str, calls: int = 50, warmup: int = 5, inference_dtype: str = "auto") -> dict:
    """Time our planner and the peer on one workload; see the module docstring."""
    w = WORKLOADS[name]
    S, A, E = w["state_dim"], w["action_dim"], w["ensemble"]
    model = EnsembleDynamics(S, A, ensemble=E, hidden=(500, 500), seed=0, inference_dtype=inference_dtype).eval()
    cost = _cost_for(name, S)
    rng = np.random.default_rng(0)
    state = rng.normal(size=S).astype(np.float32)
    if name == "A":
        i = ROACH_STATE_NAMES.index
        state[i("cos_yaw")], state[i("sin_yaw")] = 1.0, 0.0
    s0 = torch.from_numpy(state)

    planner = _make_planner(w)
    fns: dict[str, Callable[[], object]] = {"ours": lambda: planner(model, cost, state)}
    result = {
        "planner": w["planner"],
        "dtype": str(model.inference_dtype).replace("torch.", ""),
        **{k: w[k] for k in ("state_dim", "action_dim", "ensemble", "samples", "horizon")},
    }
    try:
        peer = _make_peer(model, cost, w, s0, model.predict)
        # the same weights evaluated the textbook way (normalize, concatenate, one baddbmm per
        # layer, de-normalize): what the peer gets from a plain torch model of this network
        peer_plain = _make_peer(model, cost, w, s0, model._predict_diff)

        def peer_call(p=peer):
            with torch.inference_mode():
                return p.command(torch.from_numpy(state)).numpy()

        fns["peer"] = peer_call
        fns["peer_plain"] = lambda: peer_call(peer_plain)
        result["peer"] = "pytorch_mppi.MPPI"
    except ImportError as e:  # the peer is optional
        result["peer"] = f"unavailable: {e}"
    times = _time_interleaved(fns, calls, warmup)
    result.update(_percentiles(times["ours"]))
    if "peer" in times:
        p, pp = _percentiles(times["peer"]), _percentiles(times["peer_plain"])
        result["peer_p50_ms"], result["peer_p99_ms"] = p["p50_ms"], p["p99_ms"]
        result["ratio_p50"] = result["p50_ms"] / p["p50_ms"]
        result["peer_plain_model_p50_ms"], result["peer_plain_model_p99_ms"] = pp["p50_ms"], pp["p99_ms"]
        result["ratio_p50_vs_plain_model"] = result["p50_ms"] / pp["p50_ms"]
    else:
        result["peer_p50_ms"] = result["peer_p99_ms"] = None
    # the other precision, for the record (bf16 helps only with fast native bf16 matmuls)
    other = "fp32" if model.inference_dtype == torch.bfloat16 else "bf16"
    if other == "fp32" or cpu_bf16_support():
        model.set_inference_dtype(other)
        planner.reset()
        p = _percentiles(_time_calls(lambda: planner(model, cost, state), max(5, calls // 5), 2))
        result[f"{other}_p50_ms"], result[f"{other}_p99_ms"] = p["p50_ms"], p["p99_ms"]
    return result


def _loadavg() -> float | None:
    try:
        return float(open("/proc/loadavg").read().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def run_bench_plan(calls: int = 50, warmup: int = 5, threads: int | None = None,
                   inference_dtype: str = "auto") -> dict:
    """Benchmark workloads A and B. Returns ``{"A": {...}, "B": {...}, "env": {...}}``.

    Each workload dict has ``p50_ms``, ``p99_ms`` (our planner, named in ``planner``),
    ``peer_p50_ms``, ``peer_p99_ms`` (pytorch-mppi's MPPI), ``ratio_p50`` (ours / peer),
    ``dtype`` (inference precision used) and the timing in the other precision.
    ``threads``: torch intra-op threads (default: torch's, i.e. the cores).
    """
    if threads is not None:
        torch.set_num_threads(int(threads))
    out = {name: bench_workload(name, calls, warmup, inference_dtype) for name in WORKLOADS}
    out["env"] = {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu_bf16": cpu_bf16_support(),
        # with the default (active) OpenMP wait policy, 2 threads on 2 shared cores collapse
        # under load from other processes; PASSIVE (set before torch loads) avoids that
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "loadavg_1min": _loadavg(),
        "calls": calls,
        "warmup": warmup,
    }
    return out


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=50)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--dtype", default="auto", choices=["auto", "fp32", "bf16"])
    args = ap.parse_args()
    print(json.dumps(run_bench_plan(args.calls, args.warmup, args.threads, args.dtype), indent=2))
