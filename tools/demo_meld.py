"""`hil demo meld`: MELD vs SLAC (no reward evidence) vs SAC on a history of images and rewards,
meta-trained on the training tasks and tested on held-out tasks (thesis Algorithms 7 and 8), on
the WidowX reach-to-port (tasks set by the task-reset mechanism) and the Sawyer reacher, from
the sim backends' fixed + wrist cameras (docs/meld.md).

Writes ``OUT/report.json`` ``{task: {method: {success_rate, reward, episodes, seeds, samples, ...}}}``,
``OUT/report.md``, ``OUT/curves.png`` (held-out success against environment samples, beside the
thesis' WidowX figure) and ``OUT/belief.png`` (MELD's task estimate over a held-out episode).

Every method gets the same budget per task and seed: the same random episodes to start from
(collected once), then the same environment samples or the same wall time, whichever ends first,
and the same gradient steps per collected epoch.
"""

from __future__ import annotations

import copy
import json
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

#: the thesis' WidowX cable insertion (Fig. 7.13): success on 10 unseen tasks after 50k samples
THESIS_WIDOWX = {"samples": 50_000, "success_rate": 0.96, "source": "thesis Fig. 7.13 / MELD (Zhao et al. 2020)"}
METHODS = ("meld", "slac", "sac_history")


@dataclass
class DemoConfig:
    tasks: tuple[str, ...] = ("sawyer_reach", "widowx_port")
    methods: tuple[str, ...] = METHODS
    seeds: tuple[int, ...] = (0,)
    camera_px: int = 32                  #: per view; the image is camera_px × 2·camera_px
    env_samples: int = 50_000
    time_budget_s: float | None = 900.0  #: per method, task and seed (training + collection)
    initial_episodes: int = 1
    tasks_per_epoch: int = 4
    train_steps_per_epoch: int = 40
    eval_every: int = 5
    batch: int = 32
    seq_len: int = 8
    threads: int = 2
    #: held-out WidowX tasks the trained MELD policy (first seed) then runs on the emulated rig
    rig_episodes: int = 10

    @classmethod
    def quick(cls, **kw: Any) -> DemoConfig:
        return replace(cls(time_budget_s=60.0, eval_every=1000, train_steps_per_epoch=20, rig_episodes=2), **kw)

    @classmethod
    def full(cls, **kw: Any) -> DemoConfig:
        return replace(cls(seeds=(0, 1, 2), camera_px=64, time_budget_s=None, batch=64, seq_len=8), **kw)


class DoNothing:
    """The do-nothing reference: zero joint velocity, the arm stays at its start pose."""

    name = "do_nothing"

    def __init__(self, action_dim: int):
        self.dim = action_dim

    def reset(self) -> None:
        pass

    def observe(self, image_u8: np.ndarray, reward: float) -> None:
        pass

    def act(self, deterministic: bool = False) -> np.ndarray:
        return np.zeros(self.dim)


def do_nothing_scores(tasks: tuple[str, ...] = ("sawyer_reach", "widowx_port"), seed: int = 0,
                      camera_px: int = 32) -> dict[str, Any]:
    """Held-out success and reward of :class:`DoNothing` on each task (Algorithm 8's episodes)."""
    from hilstack.learning.meld.train import meta_test
    from hilstack.tools.meld_tasks import TASKS

    out = {}
    for name in tasks:
        env = TASKS[name](camera_px=camera_px, seed=seed)
        try:
            out[name] = meta_test(env, DoNothing(env.action_dim), env.test_tasks)
        finally:
            env.close()
    return out


def reproduce_command(out: Path, quick: bool, full: bool, seed: int) -> str:
    flags = " --quick" if quick else " --full" if full else ""
    return f"MUJOCO_GL=egl hil demo meld{flags} --seed {seed} --out {out}"


def _agent_config(env: Any, cfg: DemoConfig):
    from hilstack.learning.meld.agents import AgentConfig
    from hilstack.learning.meld.model import LatentConfig

    return AgentConfig(latent=LatentConfig(image_hw=(cfg.camera_px, 2 * cfg.camera_px), action_dim=env.action_dim),
                       batch=cfg.batch, seq_len=cfg.seq_len)


def belief_trace(env: Any, agent: Any, held_out: int) -> dict[str, Any]:
    """MELD's task estimate over one held-out episode: a linear probe from the belief mean to
    the task parameters, fitted on the belief at every step of one episode on each of the first 10
    training tasks (10 × 41 beliefs; fewer episodes keep ``--quick`` short)."""
    from hilstack.learning.meld.train import apply_probe, run_episode, task_probe

    feats, params = [], []
    for task in list(env.train_tasks)[:10]:
        run_episode(env, task, lambda: agent.act(deterministic=True), agent)
        f = agent.task_features()
        feats.append(f), params.append(np.repeat(env.task_params[task][None], len(f), 0))
    params = np.concatenate(params)
    mu, sd = params.mean(0), params.std(0) + 1e-12  # the probe on standardized parameters
    w = task_probe(np.concatenate(feats), (params - mu) / sd)
    ep, info = run_episode(env, held_out, lambda: agent.act(deterministic=True), agent)
    est = apply_probe(w, agent.task_features()) * sd + mu
    return {"task": held_out, "names": list(env.task_param_names), "true": env.task_params[held_out].tolist(),
            "estimate": est.tolist(),
            "success": ep.success, "final_distance_m": info.get("distance_m")}


def run_meld_demo(out: Path, cfg: DemoConfig, command: str, log=print) -> dict[str, Any]:
    import torch

    from hilstack.learning.meld.agents import AGENTS
    from hilstack.learning.meld.replay import TaskReplay
    from hilstack.learning.meld.train import MetaTrainConfig, meta_train, run_episode
    from hilstack.tools.meld_tasks import TASKS, goal_spread

    torch.set_num_threads(cfg.threads)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    report: dict[str, Any] = {}
    runs: dict[str, Any] = {}
    traces: dict[str, Any] = {}
    rig_runs: dict[str, Any] = {}
    for task_name in cfg.tasks:
        report[task_name], runs[task_name] = {}, {}
        still: list[dict[str, Any]] = []
        for seed in cfg.seeds:
            env = TASKS[task_name](camera_px=cfg.camera_px, seed=seed)
            try:
                rng = np.random.default_rng([seed, 1])
                t0 = time.monotonic()
                shared = TaskReplay()  # the same random start for every method
                for task in env.train_tasks:
                    for _ in range(cfg.initial_episodes):
                        shared.add(run_episode(env, task, None, rng=rng)[0])
                random_s = time.monotonic() - t0
                from hilstack.learning.meld.train import meta_test

                still.append({"seed": seed, **meta_test(env, DoNothing(env.action_dim), env.test_tasks)})
                spread = goal_spread(env)
                log(f"[meld demo] {task_name} seed {seed}: {shared.n_samples} random samples in {random_s:.0f} s")
                for method in cfg.methods:
                    torch.manual_seed(seed)
                    agent = AGENTS[method](_agent_config(env, cfg))
                    mt = MetaTrainConfig(env_samples=cfg.env_samples, initial_episodes=0,
                                         tasks_per_epoch=cfg.tasks_per_epoch,
                                         train_steps_per_epoch=cfg.train_steps_per_epoch, eval_every=cfg.eval_every,
                                         time_budget_s=cfg.time_budget_s, seed=seed)
                    res = meta_train(env, agent, mt, log=log, initial_replay=copy.deepcopy(shared))
                    res.pop("replay")
                    res["random_collect_s"] = random_s
                    runs[task_name].setdefault(method, []).append({"seed": seed, **res})
                    if method == "meld" and seed == cfg.seeds[0]:
                        traces[task_name] = belief_trace(env, agent, env.test_tasks[0])
                        if task_name == "widowx_port" and cfg.rig_episodes:
                            held = env.task_params[list(env.test_tasks)[: cfg.rig_episodes]]
                            try:
                                rig_runs[task_name] = run_on_emulated_rig(agent, held, cfg.camera_px, log=log)
                            except Exception as e:  # noqa: BLE001 - a failed rig run is reported, the rest stands
                                rig_runs[task_name] = {"rig": RIG, "error": f"{type(e).__name__}: {e}"}
                                log(f"[meld rig] failed: {rig_runs[task_name]['error']}")
                report[task_name]["task_spread"] = spread
                report[task_name]["success_m"] = env.success_m
                if env.success_deg is not None:
                    report[task_name]["success_deg"] = env.success_deg
            finally:
                env.close()
        report[task_name]["do_nothing"] = {
            "success_rate": float(np.mean([r["success_rate"] for r in still])),
            "reward": float(np.mean([r["reward"] for r in still])), "reward_std": float(np.std([r["reward"] for r in still])),
            "final_distance_m": float(np.mean([r["final_distance_m"] for r in still])),
            "episodes": int(sum(r["episodes"] for r in still)), "seeds": [r["seed"] for r in still], "samples": 0}
        for method, rs in runs[task_name].items():
            fin = [r["final"] for r in rs]
            sr = np.array([f["success_rate"] for f in fin])
            rw = np.array([f["reward"] for f in fin])
            report[task_name][method] = {
                "success_rate": float(sr.mean()), "success_rate_std": float(sr.std()),
                "reward": float(rw.mean()), "reward_std": float(rw.std()),
                "episodes": int(sum(f["episodes"] for f in fin)), "seeds": [r["seed"] for r in rs],
                "samples": int(np.mean([r["samples"] for r in rs])),
                "gradient_steps": int(np.mean([r["gradient_steps"] for r in rs])),
                "final_distance_m": float(np.mean([f.get("final_distance_m", np.nan) for f in fin])),
                "stopped_by_time": any(r["stopped_by_time"] for r in rs),
                "wall_s": {k: float(np.mean([r["wall_s"][k] for r in rs])) for k in rs[0]["wall_s"]},
            }
    meta = {"command": command, "config": asdict(cfg), "wall_s": time.monotonic() - t_start,
            "created": time.strftime("%Y-%m-%d %H:%M:%S"), "thesis": THESIS_WIDOWX,
            "curves": {t: {m: [{"seed": r["seed"], "curve": r["curve"]} for r in rs] for m, rs in v.items()}
                       for t, v in runs.items()},
            "belief": traces, "rig": rig_runs}
    (out / "report.json").write_text(json.dumps({**report, "_meta": meta}, indent=1, default=float))
    (out / "report.md").write_text(markdown(report, meta))
    _plots(out, meta)
    return {**report, "_meta": meta}


def markdown(report: dict[str, Any], meta: dict[str, Any]) -> str:
    cfg = meta["config"]
    lines = ["# MELD from images", "", f"Reproduce: `{meta['command']}` ({meta['wall_s']:.0f} s wall clock, "
             f"{meta['created']}). Images {cfg['camera_px']}×{2 * cfg['camera_px']} (fixed | wrist); seeds "
             f"{list(cfg['seeds'])}; budget per method: {cfg['env_samples']} samples or "
             f"{cfg['time_budget_s']} s.", ""]
    names = {"meld": "MELD", "slac": "SLAC (no reward evidence)", "sac_history": "SAC on image+reward history"}
    for task, v in report.items():
        sp = v["task_spread"]
        crit = f"within {100 * v['success_m']:.1f} cm" + (f" and {v['success_deg']:.0f}° of the port's axis"
                                                         if "success_deg" in v else "")
        angle = (f", axes {sp['angle_mean_deg']:.1f}° (mean) / {sp['angle_max_deg']:.1f}° (max) from their mean"
                 if "angle_mean_deg" in sp else "")
        lines += [f"## {task}", "", f"Success: {crit} at the end of a 40-step episode on 10 held-out tasks. Goals "
                  f"spread {100 * sp['mean_m']:.1f} cm (mean) / {100 * sp['max_m']:.1f} cm (max) from their mean{angle}; "
                  f"the best task-blind pose would succeed on {100 * sp['task_blind_success']:.0f} % of the held-out tasks.",
                  "",
                  "| method | held-out success (mean ± std) | reward | final distance (cm) | samples | gradient steps |",
                  "|---|---|---|---|---|---|"]
        for m in cfg["methods"]:
            r = v[m]
            lines.append(f"| {names[m]} | {100 * r['success_rate']:.0f} ± {100 * r['success_rate_std']:.0f} % | "
                         f"{r['reward']:.1f} ± {r['reward_std']:.1f} | {100 * r['final_distance_m']:.1f} | "
                         f"{r['samples']} | {r['gradient_steps']} |")
        d = v["do_nothing"]
        lines += [f"| do nothing (zero velocity) | {100 * d['success_rate']:.0f} % | {d['reward']:.1f} | "
                  f"{100 * d['final_distance_m']:.1f} | 0 | 0 |", ""]
    for task, rr in meta.get("rig", {}).items():
        if "error" in rr:
            lines += [f"## {task} on the emulated rig ({rr['rig']})", "", f"The rig run failed: {rr['error']}", ""]
            continue
        lines += [f"## {task} on the emulated rig ({rr['rig']})", "",
                  f"The trained MELD policy (first seed) as a controller node, the task set by the mechanism: "
                  f"{rr['episodes']} held-out tasks, success {100 * rr['success_rate']:.0f} %, final plug error "
                  f"{100 * rr['final_position_m']:.1f} cm; inference (belief update + actor) p50 "
                  f"{rr['inference_ms']['p50']:.1f} ms / p99 {rr['inference_ms']['p99']:.1f} ms; policy period "
                  f"{rr['policy_period_s']:.3f} s (3.3 Hz: 0.300 s).", ""]
    lines.append(f"Thesis reference: WidowX cable insertion {100 * THESIS_WIDOWX['success_rate']:.0f} % on 10 unseen tasks "
                 f"after {THESIS_WIDOWX['samples']} samples ({THESIS_WIDOWX['source']}).")
    return "\n".join(lines) + "\n"


RIG = "arm_widowx_emulated"


def run_on_emulated_rig(agent: Any, task_params: np.ndarray, camera_px: int, steps: int = 40,
                        log=print) -> dict[str, Any]:
    """A MELD agent as a controller node on the emulated WidowX rig (the real Dynamixel drivers
    over a virtual link to the bench's emulator process, the rig's access control), one episode
    per mechanism pose of ``task_params`` [(rotation rad, offset m)], the task set by the mechanism.
    The rig comes up in this process through :func:`~hilstack.learning.meld.node.meld_rig` (its
    driver nodes on one server session, as `hil up` runs a one-bus rig) on a free local endpoint.
    Returns success, final plug error, inference time (p50/p99 [ms]) and the policy period achieved."""
    from hilstack.bus.ports import free_endpoint
    from hilstack.drivers.registry import skill, spec_of
    from hilstack.learning.meld.node import meld_rig
    from hilstack.tools.common import provision_credentials, rig_bus
    from hilstack.tools.meld_tasks import BenchView

    name, bus, cfg = rig_bus(RIG, free_endpoint(), need_config=True)
    provision_credentials(name, bus, cfg)
    view = BenchView(camera_px=camera_px)
    eps = []
    try:
        with meld_rig(RIG, bus, agent, view, bus_name="meld_demo", link_timeout_periods=40,
                      ready_timeout_s=120.0) as ctl:
            # home: the sim task's start pose (the sleep pose of the bench's kinematics skill)
            sleep = skill("widowx", "kinematics").SLEEP_POSE_RAD
            q_home = np.array([sleep.get(j, 0.0) for j in spec_of("widowx").joint_names()])
            for rot, off in task_params:
                pose = ctl.set_task(np.array([rot, off]), tol=np.array([0.01, 0.001]), timeout_s=20.0)
                ctl.home(q_home, timeout_s=20.0)
                ep = ctl.episode(steps)
                info = ep["infos"][-1]
                eps.append({"mechanism_pose": pose.tolist(), "success": ep["success"],
                            "position_m": info["position_m"], "angle_deg": info["angle_deg"],
                            "inference_s": ep["inference_s"], "policy_period_s": ep["policy_period_s"]})
                log(f"[meld rig] task {rot:+.3f} rad {off:+.4f} m: plug {100 * info['position_m']:.1f} cm "
                    f"{info['angle_deg']:.0f}° off, period {ep['policy_period_s']:.3f} s")
    finally:
        view.close()
    inf = np.concatenate([e["inference_s"] for e in eps]) if eps else np.zeros(1)
    return {"rig": RIG, "episodes": len(eps), "success_rate": float(np.mean([e["success"] for e in eps])),
            "final_position_m": float(np.mean([e["position_m"] for e in eps])),
            "inference_ms": {"p50": 1e3 * float(np.percentile(inf, 50)), "p99": 1e3 * float(np.percentile(inf, 99))},
            "policy_period_s": float(np.median([e["policy_period_s"] for e in eps])), "by_episode": eps}


def _plots(out: Path, meta: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = meta["curves"]
    fig, axes = plt.subplots(2, len(curves), figsize=(5.5 * len(curves), 7), squeeze=False)
    for col, (task, by_method) in enumerate(curves.items()):
        ax, axr = axes[0][col], axes[1][col]
        for m, rs in by_method.items():
            for r in rs:
                c = r["curve"]
                x = [p["samples"] for p in c]
                ax.plot(x, [p["success_rate"] for p in c], marker="o", label=f"{m} s{r['seed']}")
                axr.plot(x, [p["reward"] for p in c], marker="o", label=f"{m} s{r['seed']}")
        if task == "widowx_port":
            ax.scatter([THESIS_WIDOWX["samples"]], [THESIS_WIDOWX["success_rate"]], marker="*", s=150, c="k",
                       label="thesis WidowX insertion (Fig. 7.13)")
            ax.set_xscale("symlog", linthresh=1000)
        ax.set(title=task, ylabel="held-out success", ylim=(-0.05, 1.05))
        axr.set(xlabel="environment samples", ylabel="held-out episode reward")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=100)
    plt.close(fig)
    if meta["belief"]:
        fig, axes = plt.subplots(1, len(meta["belief"]), figsize=(5.5 * len(meta["belief"]), 4), squeeze=False)
        for ax, (task, tr) in zip(axes[0], meta["belief"].items(), strict=True):
            est = np.asarray(tr["estimate"])
            for i in range(est.shape[1]):
                line, = ax.plot(est[:, i], label=tr.get("names", [f"parameter {j}" for j in range(est.shape[1])])[i])
                ax.axhline(tr["true"][i], ls="--", c=line.get_color())
            ax.set(title=f"{task}: MELD belief's task estimate (held-out task {tr['task']})", xlabel="step",
                   ylabel="task parameter (dashed: true)")
            ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "belief.png", dpi=100)
        plt.close(fig)


def cli_meld(out: Path, quick: bool = False, full: bool = False, seed: int = 0) -> None:
    """`hil demo meld` (tools/cmd_demo.py's OTHER_DEMOS)."""
    import typer

    from hilstack.tools.common import UserError

    out = Path(out)
    if (out / "report.json").exists():
        raise UserError(f"hil demo meld: {out / 'report.json'} exists; choose another --out")
    os.environ.setdefault("MUJOCO_GL", "egl")
    seeds = (seed, seed + 1, seed + 2) if full else (seed,)
    cfg = DemoConfig.quick(seeds=seeds) if quick else DemoConfig.full(seeds=seeds) if full else DemoConfig(seeds=seeds)
    rep = run_meld_demo(out, cfg, reproduce_command(out, quick, full, seed),
                        log=lambda m: typer.echo(m, err=True))
    for task, v in rep.items():
        if task.startswith("_"):
            continue
        typer.echo(f"{task}: held-out success " + ", ".join(
            f"{m} {100 * v[m]['success_rate']:.0f} %" for m in cfg.methods) + f" ({v[cfg.methods[0]]['samples']} samples)")
    typer.echo(f"report: {out / 'report.md'}")



def run_task_inference(seeds: tuple[int, ...] = (0, 1), steps: int = 200, log=print, reward_std: float = 0.5,
                       latent_dim: int = 32) -> dict[str, Any]:
    """MELD's premise, measured on the toy reacher (goal invisible, tasks told apart only by the
    reward): train the latent model alone (ELBO, no RL) on random episodes of 8 training goals,
    then read the goal linearly from the belief at the end of random episodes on 4 held-out goals.
    With reward evidence (MELD) vs without (SLAC); the reference is the training goals' mean
    (what a belief that knows nothing of the task gives). Error = RMS over held-out episodes [goal units].
    ``reward_std``: σ of the reward likelihood (smaller weighs the reward evidence more against
    the image's); ``latent_dim``: the latent's size."""
    import torch

    from hilstack.learning.meld.model import BeliefFilter, LatentConfig, LatentModel
    from hilstack.learning.meld.replay import TaskReplay
    from hilstack.learning.meld.toy import ToyReach
    from hilstack.learning.meld.train import apply_probe, run_episode, task_probe

    torch.set_num_threads(1)
    out: dict[str, Any] = {"steps": steps, "seeds": list(seeds), "reward_std": reward_std, "latent_dim": latent_dim,
                           "by_seed": []}
    for seed in seeds:
        env = ToyReach(hw=(16, 32), episode_steps=20, n_train=32, n_test=8, seed=seed)
        rng = np.random.default_rng(seed)
        train = [run_episode(env, t, None, rng=rng)[0] for t in env.train_tasks for _ in range(3)]
        test = [run_episode(env, t, None, rng=rng)[0] for t in env.test_tasks for _ in range(2)]
        rp = TaskReplay()
        for ep in train:
            rp.add(ep)
        row: dict[str, Any] = {"seed": seed}
        goals_tr = np.stack([env.task_params[e.task] for e in train])
        goals_te = np.stack([env.task_params[e.task] for e in test])
        row["reference_rms"] = float(np.sqrt(((goals_te - goals_tr.mean(0)) ** 2).sum(1).mean()))
        for name, evidence in (("meld", True), ("slac", False)):
            torch.manual_seed(seed)
            m = LatentModel(LatentConfig(image_hw=(16, 32), action_dim=2, channels=(16, 32), reward_evidence=evidence,
                                         reward_std=reward_std, latent_dim=latent_dim))
            opt = torch.optim.Adam(m.parameters(), lr=1e-3)
            t0 = time.perf_counter()
            for _ in range(steps):
                b = rp.sample(rng, 32, 8)
                terms, _ = m.elbo(torch.as_tensor(b["images"], dtype=torch.float32) / 255.0,
                                  torch.as_tensor(b["rewards"]), torch.as_tensor(b["actions"]))
                opt.zero_grad()
                (-terms["elbo"].mean() / 8).backward()
                opt.step()
            f = BeliefFilter(m)

            def final_belief(ep, f=f):
                f.reset()
                for i in range(len(ep.images)):
                    f.update(ep.images[i], float(ep.rewards[i]))
                    if i < len(ep.actions):
                        f.act(ep.actions[i])
                return f.mu[0].numpy()

            ftr, fte = np.stack([final_belief(e) for e in train]), np.stack([final_belief(e) for e in test])
            mu, sd = ftr.mean(0), ftr.std(0) + 1e-6
            w = task_probe((ftr - mu) / sd, goals_tr, ridge=1.0)
            est = apply_probe(w, (fte - mu) / sd)
            row[name] = {"held_out_rms": float(np.sqrt(((est - goals_te) ** 2).sum(1).mean())),
                         "train_s": time.perf_counter() - t0}
            log(f"[task inference] seed {seed} {name}: held-out goal RMS {row[name]['held_out_rms']:.3f} "
                f"(reference {row['reference_rms']:.3f})")
        out["by_seed"].append(row)
    for name in ("meld", "slac"):
        v = np.array([r[name]["held_out_rms"] for r in out["by_seed"]])
        out[name] = {"held_out_rms_mean": float(v.mean()), "held_out_rms_std": float(v.std())}
    ref = np.array([r["reference_rms"] for r in out["by_seed"]])
    out["reference"] = {"held_out_rms_mean": float(ref.mean()), "held_out_rms_std": float(ref.std())}
    return out


def run_curve(task: str, method: str, seed: int, samples: int, updates_per_sample: float = 0.25,
              camera_px: int = 32, batch: int = 32, latent_dim: int = 32, reward_std: float = 0.5,
              entropy_per_dim: float = -1.0, reward_scale: float = 1.0, eval_every_samples: int = 800,
              time_budget_s: float | None = None, threads: int = 1, log=print) -> dict[str, Any]:
    """One learner's held-out learning curve (Algorithms 7/8) on ``task`` with the knobs the
    diagnostics vary: gradient steps per environment sample, batch, latent size, the reward's σ
    in the ELBO, SAC's entropy target and reward scale. ``task="toy"``: the point reacher of
    learning/meld/toy.py in 16×32 images (20 training / 10 held-out goals, 20 steps), seconds per
    thousand steps; else a robot task of tools/meld_tasks.py at ``camera_px``. Returns the curve
    (success and reward against samples and gradient steps) and the collection and learning rates."""
    import torch

    from hilstack.learning.meld.agents import AGENTS, AgentConfig
    from hilstack.learning.meld.model import LatentConfig
    from hilstack.learning.meld.sac import SacConfig
    from hilstack.learning.meld.train import MetaTrainConfig, meta_train

    torch.set_num_threads(threads)
    if task == "toy":
        from hilstack.learning.meld.toy import ToyReach

        env = ToyReach(hw=(16, 32), episode_steps=20, n_train=20, n_test=10, seed=seed)
        hw, channels = (16, 32), (16, 32)
    else:
        from hilstack.tools.meld_tasks import TASKS

        env = TASKS[task](camera_px=camera_px, seed=seed)
        hw, channels = (camera_px, 2 * camera_px), LatentConfig.channels
    tasks_per_epoch = 4
    per_epoch = tasks_per_epoch * env.episode_steps
    steps = max(1, round(updates_per_sample * per_epoch))
    acfg = AgentConfig(latent=LatentConfig(image_hw=hw, action_dim=env.action_dim, channels=channels,
                                           latent_dim=latent_dim, reward_std=reward_std),
                       sac=SacConfig(target_entropy_per_dim=entropy_per_dim, reward_scale=reward_scale), batch=batch)
    torch.manual_seed(seed)
    agent = AGENTS[method](acfg)
    mt = MetaTrainConfig(env_samples=samples, tasks_per_epoch=tasks_per_epoch, train_steps_per_epoch=steps,
                         eval_every=max(1, eval_every_samples // per_epoch), time_budget_s=time_budget_s, seed=seed)
    try:
        res = meta_train(env, agent, mt, log=log)
    finally:
        env.close()
    res.pop("replay")
    for p in res["curve"]:
        p["gradient_steps"] = p["epoch"] * steps
    w = res["wall_s"]
    collected = res["samples"]
    return {"task": task, "method": method, "seed": seed, "updates_per_sample": updates_per_sample,
            "train_steps_per_epoch": steps, "camera_px": camera_px, "batch": batch, "latent_dim": latent_dim,
            "reward_std": reward_std, "entropy_per_dim": entropy_per_dim, "reward_scale": reward_scale,
            "threads": threads, "load_avg": os.getloadavg(), **res,
            "samples_per_s": collected / max(w["collect"], 1e-9),
            "gradient_steps_per_s": res["gradient_steps"] / max(w["train"], 1e-9)}


def run_cost(sizes: tuple[int, ...] = (16, 32, 64), batches: tuple[int, ...] = (32, 128, 512), steps: int = 3,
             log=print) -> dict[str, Any]:
    """What MELD and its baselines cost on this CPU, in *CPU seconds* of one process on one torch
    thread (``time.process_time``: on a shared machine the wall clock measures the other jobs;
    CPU time does not, to first order): per gradient step of each learner at each image size
    (batch 32 sequences of 8), per MELD step at larger batches (Table 7.1's 512) at 32×64, and per
    collected sample of each robot task with the cameras at each size and without (rendering's share)."""
    import torch

    from hilstack.learning.meld.agents import AGENTS, AgentConfig
    from hilstack.learning.meld.model import LatentConfig
    from hilstack.learning.meld.replay import ImageEpisode, TaskReplay
    from hilstack.learning.meld.train import run_episode
    from hilstack.tools.meld_tasks import TASKS

    torch.set_num_threads(1)
    out: dict[str, Any] = {"load_avg": os.getloadavg(), "cpu_s_per_step": {}, "cpu_s_per_sample": {}}

    def step_cost(method: str, px: int, batch: int) -> float:
        rng = np.random.default_rng(0)
        rp, hw = TaskReplay(), (px, 2 * px)
        for task in range(4):
            rp.add(ImageEpisode(rng.integers(0, 255, (41, *hw, 3), dtype=np.uint8),
                                rng.normal(size=41).astype(np.float32), rng.uniform(-1, 1, (40, 7)).astype(np.float32),
                                task))
        torch.manual_seed(0)
        agent = AGENTS[method](AgentConfig(latent=LatentConfig(image_hw=hw, action_dim=7), batch=batch))
        agent.train_step(rp, rng)  # warm-up (optimizers, allocations)
        n = steps if batch <= 128 else 1
        t = time.process_time()
        for _ in range(n):
            agent.train_step(rp, rng)
        return (time.process_time() - t) / n

    for px in sizes:
        for m in ("meld", "sac_history"):
            out["cpu_s_per_step"][f"{m}_{px}x{2 * px}_b32"] = v = step_cost(m, px, 32)
            log(f"[cost] {m} {px}x{2 * px} batch 32: {v:.3f} CPU s per gradient step")
    for b in batches:
        if b != 32:
            out["cpu_s_per_step"][f"meld_32x64_b{b}"] = v = step_cost("meld", 32, b)
            log(f"[cost] meld 32x64 batch {b}: {v:.3f} CPU s per gradient step")
    for task in ("sawyer_reach", "widowx_port"):
        for px in (None, *sizes):
            env = TASKS[task](camera_px=px or sizes[0], cameras=px is not None)
            try:
                rng = np.random.default_rng(0)
                run_episode(env, env.train_tasks[0], None, rng=rng)  # warm-up (renderer, first task)
                t = time.process_time()
                run_episode(env, env.train_tasks[1], None, rng=rng)
                key = f"{task}_{px}x{2 * px}" if px else f"{task}_no_cameras"
                out["cpu_s_per_sample"][key] = v = (time.process_time() - t) / env.episode_steps
                log(f"[cost] {key}: {1e3 * v:.1f} CPU ms per sample")
            finally:
                env.close()
    out["load_avg_after"] = os.getloadavg()
    return out


def main(argv: list[str] | None = None) -> None:
    """The probes behind docs/meld.md: task inference without RL (toy), the do-nothing scores (still),
    SAC on the true state and goal of a robot task (oracle: the lower bound MELD is measured against)."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m hilstack.tools.demo_meld", description=main.__doc__)
    ap.add_argument("probe", choices=("toy", "still", "oracle", "curve", "cost"))
    ap.add_argument("out", type=Path, help="JSON file to write (never overwritten)")
    ap.add_argument("steps", type=int, nargs="?", default=200, help="model-only training steps (toy)")
    ap.add_argument("--reward-std", type=float, default=0.5, help="toy, curve: σ of the reward likelihood")
    ap.add_argument("--latent-dim", type=int, default=32, help="toy, curve: latent size")
    ap.add_argument("--task", default="sawyer_reach", help="oracle, curve: the robot task (curve: or toy)")
    ap.add_argument("--samples", type=int, default=8000, help="oracle: environment samples")
    ap.add_argument("--updates-per-sample", type=float, default=1.0, help="oracle, curve: gradient steps per sample")
    ap.add_argument("--seed", type=int, default=0, help="oracle, curve: seed (also draws the Sawyer's goals)")
    ap.add_argument("--method", choices=("meld", "slac", "sac_history"), default="meld", help="curve: the learner")
    ap.add_argument("--camera-px", type=int, default=32, help="curve: image height (width twice)")
    ap.add_argument("--batch", type=int, default=32, help="curve: sequences per gradient step")
    ap.add_argument("--entropy-per-dim", type=float, default=-1.0, help="curve: SAC's target entropy per action dim")
    ap.add_argument("--reward-scale", type=float, default=1.0, help="curve: SAC's reward scale")
    ap.add_argument("--eval-every", type=int, default=800, help="curve: samples between held-out evaluations")
    ap.add_argument("--time-budget", type=float, default=None, help="curve: stop after this much learning [s]")
    ap.add_argument("--threads", type=int, default=1, help="curve: torch threads")
    args = ap.parse_args(argv)
    if args.out.exists():
        raise SystemExit(f"{args.out} exists; choose another path")
    os.environ.setdefault("MUJOCO_GL", "egl")
    if args.probe == "cost":
        res = run_cost(log=lambda m: print(m, flush=True))
    elif args.probe == "curve":
        res = run_curve(args.task, args.method, args.seed, args.samples, args.updates_per_sample, args.camera_px,
                        args.batch, args.latent_dim, args.reward_std, args.entropy_per_dim, args.reward_scale,
                        args.eval_every, args.time_budget, args.threads, log=lambda m: print(m, flush=True))
    elif args.probe == "oracle":
        res = run_oracle(args.task, args.samples, args.updates_per_sample, args.seed)
    elif args.probe == "still":
        res = do_nothing_scores()
    else:
        res = run_task_inference(steps=args.steps, reward_std=args.reward_std, latent_dim=args.latent_dim)
    args.out.write_text(json.dumps(res, indent=1))


def run_oracle(task: str, samples: int, updates_per_sample: float, seed: int) -> dict[str, Any]:
    """SAC on the true joint angles and goal of ``task`` (cameras off, one torch thread)."""
    import torch

    from hilstack.learning.meld.diagnose import StateSacConfig, state_sac
    from hilstack.tools.meld_tasks import TASKS

    torch.set_num_threads(1)
    env = TASKS[task](camera_px=32, seed=seed, cameras=False)
    try:
        return state_sac(env, StateSacConfig(samples=samples, updates_per_sample=updates_per_sample, seed=seed),
                         log=lambda m: print(m, flush=True))
    finally:
        env.close()


if __name__ == "__main__":
    main()
