"""Planning-latency benchmark: our planners vs pytorch-mppi's MPPI on the same model.

Workloads (the two systems of the research):

* **A** VelociRoACH: state 24, action 2, one model, 500 samples, horizon 4, random shooting,
  path-following cost on a figure-8.
* **B** Shadow Hand / PDDM: state 40, action 24, ensemble of 3, 700 samples, horizon 7, PDDM
  (γ=20, β=0.7), quadratic goal cost on the first 6 state channels (two ball positions).
* **baoding**: the planner and ensemble exactly as ``hilstack.control.planners.BAODING_PDDM``
  configures them (the one definition the Baoding demo uses): state 36, action 20, the
  reference code's sampler (β=0.6, the action filter, σ 0.9, 10 % low noise), quadratic goal
  cost on the last 6 state channels.

All use a 2x500 ReLU MLP (:class:`hilstack.learning.dynamics.EnsembleDynamics`, random init).
The peer is ``pytorch_mppi.MPPI`` with the same cost (as its ``terminal_state_cost``,
which receives the whole predicted trajectory), the same samples, horizon and noise σ,
``lambda_ = 1/γ`` (which gives the same e^{γ(R - max R)} weights), and for the ensemble
``rollout_samples = E`` with each rollout sample routed to one member. It runs twice: on
our model object (``peer_*``: the difference is the planner's alone) and on the same weights
as a list of ``nn.Sequential`` members (``peer_plain_model_*``: what a user would write).
Everything runs under ``torch.inference_mode``, interleaved call by call.

Throughput: ``gflops`` is :func:`plan_flops` (the MLP's multiply-adds in one planning call)
over our p50; ``matmul_gflops`` the same count over the p50 of the bare batched matmuls of
those shapes (``torch.bmm``, no planner, no bias, no ReLU), timed in the same run, so their
ratio says how much of the machine's matmul rate the planner gets under today's load.

``run_bench_plan`` returns latency percentiles in milliseconds over ``calls`` planning calls
after ``warmup`` calls. Use it through ``hil bench plan --json`` or
``python -m hilstack.tools.bench_plan``.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
import torch
from torch import nn

from hilstack.control.costs import PathCost
from hilstack.control.paths import make_path
from hilstack.control.planners import BAODING_PDDM, PDDM, RandomShooting
from hilstack.learning.dynamics import EnsembleDynamics, cpu_bf16_support

__all__ = ["run_bench_plan", "WORKLOADS", "plan_flops", "PlainEnsemble"]

ROACH_STATE_NAMES = [
    "x", "y", "z", "vx", "vy", "vz", "cos_roll", "sin_roll", "cos_pitch", "sin_pitch",
    "cos_yaw", "sin_yaw", "wx", "wy", "wz", "cos_left_crank", "sin_left_crank",
    "cos_right_crank", "sin_right_crank", "left_crank_vel", "right_crank_vel",
    "left_bemf", "right_bemf", "vbat",
]  # fmt: skip

WORKLOADS = {
    "A": {"state_dim": 24, "action_dim": 2, "ensemble": 1, "samples": 500, "horizon": 4,
          "hidden": (500, 500), "planner": "random_shooting"},
    "B": {"state_dim": 40, "action_dim": 24, "ensemble": 3, "samples": 700, "horizon": 7,
          "hidden": (500, 500), "planner": "pddm"},
    "baoding": {**BAODING_PDDM.model_kwargs(), "samples": BAODING_PDDM.samples,
                "horizon": BAODING_PDDM.horizon, "planner": "baoding_pddm"},
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


def plan_flops(ensemble: int, samples: int, horizon: int, layer_sizes: Sequence[int]) -> int:
    """Floating-point operations of the MLP in one planning call (multiply and add = 2).

    Every one of ``horizon`` steps evaluates ``ensemble x samples`` inputs through the layers
    ``layer_sizes[i] -> layer_sizes[i+1]``: ``2 E N H Σ_i d_i d_{i+1}``. Bias adds, ReLUs,
    normalization and the planner's own work are left out (they are < 1 % at 2x500).
    """
    macs = sum(int(a) * int(b) for a, b in zip(layer_sizes[:-1], layer_sizes[1:], strict=False))
    return 2 * int(ensemble) * int(samples) * int(horizon) * macs


def _layer_sizes(w: dict) -> list[int]:
    return [w["state_dim"] + w["action_dim"], *w["hidden"], w["state_dim"]]


class PlainEnsemble:
    """The weights of an :class:`EnsembleDynamics` as E ``nn.Sequential`` MLPs: the model a user
    would write (normalize, concatenate, one ``Linear``/``ReLU`` stack per member, loop over
    members, de-normalize). Same contract as :meth:`EnsembleDynamics.predict`:
    ``state [B, S] | [E, B, S]``, ``action [B, A] | [E, B, A]`` -> ``[E, B, S]``.
    """

    def __init__(self, model: EnsembleDynamics) -> None:
        self.model = model  # for the normalization statistics
        self.members: list[nn.Sequential] = []
        n = len(model.weights)
        with torch.no_grad():
            for e in range(model.ensemble):
                layers: list[nn.Module] = []
                for i, (w, b) in enumerate(zip(model.weights, model.biases, strict=True)):
                    lin = nn.Linear(w.shape[1], w.shape[2])
                    lin.weight.copy_(w[e].T)  # nn.Linear stores [out, in]
                    lin.bias.copy_(b[e, 0])
                    layers.append(lin)
                    if i < n - 1:
                        layers.append(nn.ReLU())
                self.members.append(nn.Sequential(*layers).eval())

    def __call__(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        m, E = self.model, len(self.members)
        s = state if state.dim() == 3 else state.unsqueeze(0).expand(E, -1, -1)
        a = action if action.dim() == 3 else action.unsqueeze(0).expand(E, -1, -1)
        x = (torch.cat([s, a], dim=-1) - m.input_mean) / m.input_std
        y = torch.stack([net(x[e]) for e, net in enumerate(self.members)])
        return s + y * m.delta_std + m.delta_mean


def _cost_for(name: str, S: int):
    """Trajectory cost ``(states [E,N,H+1,S], actions [N,H,A]) -> [E,N]`` of a workload."""
    if name == "A":
        return PathCost(make_path("figure8"), ROACH_STATE_NAMES)
    goal = torch.linspace(-0.1, 0.1, 6)
    # B: the balls are the first 6 channels; baoding: the last 6 (after 24 angles + 24 velocities)
    balls = slice(0, 6) if name == "B" else slice(S - 6, S)

    def hand_cost(states, actions):
        # ball positions to the goal, plus a small action magnitude term
        pos = states[..., 1:, balls]
        return ((pos - goal) ** 2).sum(dim=(-1, -2)) + 1e-3 * (actions**2).sum(dim=(-1, -2))

    return hand_cost


def _make_planner(w: dict):
    if w["planner"] == "baoding_pddm":
        return BAODING_PDDM.planner(seed=0)
    kw = dict(horizon=w["horizon"], samples=w["samples"], action_dim=w["action_dim"], seed=0)
    if w["planner"] == "random_shooting":
        return RandomShooting(-1.0, 1.0, **kw)
    return PDDM(-1.0, 1.0, gamma=GAMMA, beta=BETA, sigma=SIGMA, **kw)


def _make_peer(cost, w: dict, s0: torch.Tensor, predict, sigma: float):
    from hilstack.configs.extras import require

    MPPI = require("pytorch_mppi", "hil bench plan's peer").MPPI  # noqa: N806 - the peer's class

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
        noise_sigma=(sigma**2) * torch.eye(A),
        num_samples=K,
        horizon=w["horizon"],
        lambda_=1.0 / GAMMA,
        u_min=-torch.ones(A),
        u_max=torch.ones(A),
        rollout_samples=E,
        terminal_state_cost=terminal,
    )


def _make_matmuls(w: dict, dtype: torch.dtype) -> Callable[[], None]:
    """The bare batched matmuls of one planning call: for each of H steps and each layer,
    ``bmm([E, N, d_in], [E, d_in, d_out])`` into a preallocated output."""
    E, N, H = w["ensemble"], w["samples"], w["horizon"]
    sizes = _layer_sizes(w)
    g = torch.Generator().manual_seed(0)
    xs = [torch.randn(E, N, a, generator=g).to(dtype) for a in sizes[:-1]]
    ws = [torch.randn(E, a, b, generator=g).to(dtype) for a, b in zip(sizes[:-1], sizes[1:], strict=False)]
    outs = [torch.empty(E, N, b, dtype=dtype) for b in sizes[1:]]

    def run() -> None:
        with torch.inference_mode():
            for _ in range(H):
                for x, wt, o in zip(xs, ws, outs, strict=True):
                    torch.bmm(x, wt, out=o)

    return run


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
    """Time our planner, the two peers and the bare matmuls on one workload (module docstring)."""
    w = WORKLOADS[name]
    S, A, E = w["state_dim"], w["action_dim"], w["ensemble"]
    model = EnsembleDynamics(S, A, ensemble=E, hidden=w["hidden"], seed=0, inference_dtype=inference_dtype).eval()
    cost = _cost_for(name, S)
    rng = np.random.default_rng(0)
    state = rng.normal(size=S).astype(np.float32)
    if name == "A":
        i = ROACH_STATE_NAMES.index
        state[i("cos_yaw")], state[i("sin_yaw")] = 1.0, 0.0
    s0 = torch.from_numpy(state)

    planner = _make_planner(w)
    flops = plan_flops(E, w["samples"], w["horizon"], _layer_sizes(w))
    fns: dict[str, Callable[[], object]] = {
        "ours": lambda: planner(model, cost, state),
        "matmul": _make_matmuls(w, model.inference_dtype),
    }
    result = {
        "planner": w["planner"],
        "dtype": str(model.inference_dtype).replace("torch.", ""),
        **{k: w[k] for k in ("state_dim", "action_dim", "ensemble", "samples", "horizon")},
        "hidden": list(w["hidden"]),
        "gflop_per_plan": flops / 1e9,
    }
    try:
        sigma = float(planner.sigma[0]) if isinstance(planner, PDDM) else SIGMA
        peer = _make_peer(cost, w, s0, model.predict, sigma)
        peer_plain = _make_peer(cost, w, s0, PlainEnsemble(model), sigma)

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
    result["gflops"] = flops / 1e9 / (result["p50_ms"] / 1e3)
    result["matmul_gflops"] = flops / 1e9 / (_percentiles(times["matmul"])["p50_ms"] / 1e3)
    if "peer" in times:
        p, pp = _percentiles(times["peer"]), _percentiles(times["peer_plain"])
        result["peer_p50_ms"], result["peer_p99_ms"] = p["p50_ms"], p["p99_ms"]
        result["ratio_p50"] = result["p50_ms"] / p["p50_ms"]
        result["peer_plain_model_p50_ms"], result["peer_plain_model_p99_ms"] = pp["p50_ms"], pp["p99_ms"]
        result["ratio_p50_vs_plain_model"] = result["p50_ms"] / pp["p50_ms"]
    else:
        result["peer_p50_ms"] = result["peer_p99_ms"] = result["peer_plain_model_p50_ms"] = None
    # the other precision, for the record (bf16 helps only with fast native bf16 matmuls)
    other = "fp32" if model.inference_dtype == torch.bfloat16 else "bf16"
    if other == "fp32" or cpu_bf16_support():
        model.set_inference_dtype(other)
        planner.reset()
        p = _percentiles(_time_calls(lambda: planner(model, cost, state), max(5, calls // 5), 2))
        result[f"{other}_p50_ms"], result[f"{other}_p99_ms"] = p["p50_ms"], p["p99_ms"]
    return result


def _plan_cost(evaluator: PDDM, model: EnsembleDynamics, cost, s0: torch.Tensor, plan: torch.Tensor) -> float:
    """Ensemble-mean cost of one action sequence ``plan [H, A]`` from ``s0`` under ``model``."""
    with torch.inference_mode():
        states = evaluator.rollout(model, s0, plan.unsqueeze(0))
        return float(evaluator.score(cost, states, plan.unsqueeze(0))[0])


def bench_baoding_levers(calls: int = 50, warmup: int = 5, quality_seeds: int = 5) -> dict:
    """Speed levers on the Baoding planner, timed interleaved with the configuration itself.

    * ``samples_350``: half the samples (K=350), same model: half the FLOPs.
    * ``tuned_chunks``: the same weights with the batch split measured fastest on this
      machine (:meth:`EnsembleDynamics.tune_inference`); ``chunks`` says which.
    * ``bf16``: the same weights in bfloat16, only when the CPU has native bf16
      (:func:`cpu_bf16_support`); otherwise reported as ``{"skipped": ...}``.
    * ``hidden_2x250``: the public reference code's 2x250 network. A different model, so its
      plan quality cannot be compared on a fixed model; only its latency is reported.

    Plan quality (``plan_cost_ratio``): for ``quality_seeds`` seeds, the configured planner
    and the lever each plan once from the same start (fresh planner, that seed); the returned
    plans are scored under the fp32 2x500 model and the ratio of the mean costs is reported
    (lower is better, 1.0 = no change). This is a fixed synthetic problem (random weights, the
    bench's goal cost), not the closed-loop return the Baoding demo will measure.
    """
    cfg = BAODING_PDDM
    S = cfg.state_dim
    cost = _cost_for("baoding", S)
    state = np.random.default_rng(0).normal(size=S).astype(np.float32)
    s0 = torch.from_numpy(state)
    base_model = EnsembleDynamics(**cfg.model_kwargs(), seed=0, inference_dtype="fp32").eval()
    variants: dict[str, tuple[EnsembleDynamics, Callable[[int], PDDM]]] = {
        "configured": (base_model, lambda seed: cfg.planner(seed)),
        "samples_350": (base_model, lambda seed: replace(cfg, samples=350).planner(seed)),
    }
    out: dict[str, dict] = {}
    support = cpu_bf16_support()
    if support:
        bf = EnsembleDynamics(**cfg.model_kwargs(), seed=0, inference_dtype="bf16").eval()
        variants["bf16"] = (bf, lambda seed: cfg.planner(seed))
    else:
        out["bf16"] = {"skipped": "no native bf16 on this CPU (no amx_bf16/avx512_bf16 flag)"}
    tuned = EnsembleDynamics(**cfg.model_kwargs(), seed=0, inference_dtype="fp32").eval()
    out["tuned_chunks"] = {"chunks": tuned.tune_inference(cfg.samples),
                           "default_chunks": EnsembleDynamics._chunks_for(cfg.samples)}
    variants["tuned_chunks"] = (tuned, lambda seed: cfg.planner(seed))
    small = replace(cfg, hidden=(250, 250))
    small_model = EnsembleDynamics(**small.model_kwargs(), seed=0).eval()
    timed = {**variants, "hidden_2x250": (small_model, lambda seed: small.planner(seed))}

    planners = {k: make(0) for k, (_, make) in timed.items()}
    fns = {k: (lambda k=k: planners[k](timed[k][0], cost, state)) for k in timed}
    try:  # the plain-model peer again, in this run, so every lever has its ratio to it
        peer = _make_peer(cost, WORKLOADS["baoding"], s0, PlainEnsemble(base_model), float(planners["configured"].sigma[0]))

        def peer_call():
            with torch.inference_mode():
                return peer.command(torch.from_numpy(state)).numpy()

        fns["peer_plain"] = peer_call
    except ImportError:  # the peer is optional
        pass
    times = _time_interleaved(fns, calls, warmup)
    base = _percentiles(times["configured"])
    plain = _percentiles(times["peer_plain"])["p50_ms"] if "peer_plain" in times else None
    evaluator = cfg.planner(0)
    for k in timed:
        if k == "configured":
            continue
        p = _percentiles(times[k])
        out[k] = {**out.get(k, {}), **p, "ratio_p50_vs_configured": p["p50_ms"] / base["p50_ms"],
                  "ratio_p50_vs_plain_model": None if plain is None else p["p50_ms"] / plain}
    out["configured_p50_ms"], out["peer_plain_model_p50_ms"] = base["p50_ms"], plain

    def mean_plan_cost(model: EnsembleDynamics, make: Callable[[int], PDDM]) -> float:
        costs = []
        for seed in range(quality_seeds):
            pl = make(seed)
            pl(model, cost, state)
            costs.append(_plan_cost(evaluator, base_model, cost, s0, pl.last_plan))
        return float(np.mean(costs))

    base_cost = mean_plan_cost(*variants["configured"])
    for k, (model, make) in variants.items():
        if k != "configured":
            out[k]["plan_cost_ratio"] = mean_plan_cost(model, make) / base_cost
            out[k]["quality_seeds"] = quality_seeds
    out["hidden_2x250"]["plan_cost_ratio"] = None  # a different model: see the docstring
    return out


BUDGET_MS = 100.0  # the 10 Hz control period


def run_bench_plan(calls: int = 50, warmup: int = 5, threads: int | None = None,
                   inference_dtype: str = "auto", quality_seeds: int = 5) -> dict:
    """Benchmark workloads A, B and baoding. Returns ``{"A", "B", "baoding", "env"}``.

    Each workload dict has ``p50_ms``, ``p99_ms`` (our planner, named in ``planner``),
    ``peer_p50_ms``, ``peer_p99_ms`` (pytorch-mppi's MPPI on our model), ``ratio_p50``
    (ours / peer), ``peer_plain_model_p50_ms`` / ``_p99_ms`` (MPPI on an ``nn.Sequential``
    ensemble of the same weights), ``ratio_p50_vs_plain_model``, ``gflops`` (achieved),
    ``matmul_gflops`` (bare matmuls of the same shapes, same run), ``dtype`` (inference
    precision used) and the timing in the other precision. ``baoding`` adds ``levers``
    (:func:`bench_baoding_levers`) and the goals: ``p99_within_budget`` (p99 < 100 ms) and
    ``within_half_plain_peer`` (p50 ≤ 0.5x the plain-model peer's p50).
    ``threads``: torch intra-op threads (default: torch's, i.e. the cores).
    ``env.loadavg`` is ``os.getloadavg()`` at the end: the machine may be shared, so read
    the ratios (same run), not the absolute times.
    """
    if threads is not None:
        torch.set_num_threads(int(threads))
    load_start = os.getloadavg()
    out = {name: bench_workload(name, calls, warmup, inference_dtype) for name in WORKLOADS}
    b = out["baoding"]
    b["budget_ms"] = BUDGET_MS
    b["p99_within_budget"] = b["p99_ms"] < BUDGET_MS
    b["within_half_plain_peer"] = (
        None if b["peer_plain_model_p50_ms"] is None else b["p50_ms"] <= 0.5 * b["peer_plain_model_p50_ms"])
    b["levers"] = bench_baoding_levers(calls, warmup, quality_seeds)
    out["env"] = {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu_bf16": cpu_bf16_support(),
        # with the default (active) OpenMP wait policy, 2 threads on 2 shared cores collapse
        # under load from other processes; PASSIVE (set before torch loads) avoids that
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "loadavg_start": list(load_start),  # 1, 5, 15 min (os.getloadavg)
        "loadavg": list(os.getloadavg()),
        "cpu_count": os.cpu_count(),
        "calls": calls,
        "warmup": warmup,
    }
    return out


def main(argv: list[str] | None = None) -> None:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m hilstack.tools.bench_plan", description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=50)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--dtype", default="auto", choices=["auto", "fp32", "bf16"])
    ap.add_argument("--quality-seeds", type=int, default=5)
    args = ap.parse_args(argv)
    print(json.dumps(run_bench_plan(args.calls, args.warmup, args.threads, args.dtype, args.quality_seeds), indent=2))


if __name__ == "__main__":
    main()
