"""MOLe: meta-learning for online learning (Nagabandi, Finn, Levine 2019; thesis ch. 6).

A mixture of dynamics models, one per task (condition) met so far, each adapted online from
a meta-learned prior θ* (the GrBAL θ*). Tasks follow a Chinese restaurant process (CRP):
with soft counts ``n_i`` (the summed posteriors of task i so far) and concentration α,

    P(T_t = i)   = n_i / (Σ_j n_j + α)        an existing task i
    P(T_t = new) = α   / (Σ_j n_j + α)        a new task, whose parameters start at θ*

Online EM, one E-step and one M-step per time step on the last K transitions D_t:

* E-step: ``P(T_t = i | D_t) ∝ p(D_t | θ_i) P(T_t = i)`` with the Gaussian likelihood of
  fixed unit variance in the model's normalized delta units,
  ``log p(D_t | θ) = −½ Σ_{transitions, channels} err²`` (+ a constant that cancels),
  scored on the newest ``score`` transitions of the window.
* The new task's candidate parameters are θ* after the meta-learned inner step (GrBAL's
  ψ) on the older transitions of the window, scored on the newest ones: θ* is trained to
  be good *after* one step, not before, and fitting and scoring on the same transitions
  would favour the candidate by overfitting. (The paper starts a new task at θ*; with the
  prior itself as the candidate, a task adapted to the first condition beat θ* on every
  later condition in our tests and no second task was ever created.)
* A new task is created only when its posterior beats every existing task's; otherwise the
  posterior is renormalized over the existing tasks.
* M-step: every task takes a gradient step weighted by its posterior,
  ``θ_i ← θ_i − β · P(T_t = i | D_t) · ∇θ L(θ_i; D_t)`` (β = 0.01, the thesis' model lr);
  then ``n_i += P(T_t = i | D_t)``.

An old task is *recalled* when its parameters explain the new data better than every
other task and the prior: its posterior wins again, no task is created. The MPC plans with
the most probable task's model; the update publishes those parameters, and
``info["posterior"]`` (one entry per task), ``info["task"]`` and ``info["tasks_created"]``.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch.func import grad

from hilstack.learning.adaptation.base import Adapter
from hilstack.learning.adaptation.grbal import adapt
from hilstack.learning.adaptation.model import AdaptiveMLP, Params


def crp_log_prior(counts: torch.Tensor, alpha: float) -> torch.Tensor:
    """``log P(T = i)`` for the L existing tasks (soft counts ``[L]``) and a new one: ``[L + 1]``."""
    c = torch.cat([counts.to(torch.float64), torch.tensor([float(alpha)], dtype=torch.float64)])
    return torch.log(c) - torch.log(c.sum())


def task_posterior(log_lik: torch.Tensor, counts: torch.Tensor, alpha: float) -> torch.Tensor:
    """Posterior over the L existing tasks and a new one, ``[L + 1]``, from ``log_lik [L + 1]``."""
    return torch.softmax(log_lik.to(torch.float64) + crp_log_prior(counts, alpha), dim=0)


class MoleAdapter(Adapter):
    """Mixture of online-adapted models with a CRP prior (see the module docstring).

    Args:
        model: θ* (the meta-learned prior) and normalization.
        psi: the meta-learned step size of the prior (GrBAL's ψ), for new-task candidates.
        window: K, past transitions each E/M step uses (thesis: 16).
        score: how many of the newest transitions the E-step scores (default K // 2).
        lr: β, the M-step's step size (thesis: 0.01); 0 turns the M-step off (tasks stay the
            candidates they were created as).
        alpha: CRP concentration (thesis: 1).
        max_tasks: a bound on memory; past it no task is created (counted in ``info``).
        adapt_params, clip: the prior's step (GrBAL's subset and inner-gradient cap) for the
            new-task candidate (None: all parameters, no cap).
    """

    name = "mole"

    def __init__(self, model: AdaptiveMLP, psi: Params, window: int = 16, lr: float = 0.01, alpha: float = 1.0,
                 max_tasks: int = 32, score: int | None = None, adapt_params: list[str] | None = None,
                 clip: float | None = None):
        super().__init__(model, window)
        if not alpha > 0 or not (math.isfinite(lr) and lr >= 0):
            raise ValueError(f"mole needs alpha > 0 and a finite lr >= 0, got alpha={alpha}, lr={lr}")
        if window < 2:
            raise ValueError(f"mole needs a window of >= 2 transitions (fit and score), got {window}")
        self.psi = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in psi.items()}
        self.lr, self.alpha, self.max_tasks = float(lr), float(alpha), int(max_tasks)
        self.score = int(score) if score is not None else self.window // 2
        self.adapt_params = list(adapt_params) if adapt_params is not None else None
        self.clip = None if clip is None else float(clip)
        if not 1 <= self.score < self.window:
            raise ValueError(f"mole score must be in [1, window), got {self.score}")
        self._grad = grad(model.loss)
        self.reset()

    def reset(self) -> None:
        super().reset()
        self.tasks: list[Params] = []
        self.counts = torch.zeros(0, dtype=torch.float64)
        self.refused = 0

    def _log_lik(self, params: Params, s, a, n) -> float:
        with torch.no_grad():
            return float(-0.5 * self.model.loss(params, s, a, n) * n.numel())

    def _update(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        if not self._buf:
            return {}, {"posterior": [], "task": -1, "tasks_created": 0}
        s, a, n = self.window_tensors()
        m = s.shape[0]
        k = min(self.score, m - 1) if m > 1 else m
        fit, sc = slice(0, m - k), slice(m - k, m)
        if m > 1:
            cand = {key: v.detach() for key, v in adapt(self.model, self.theta_star, self.psi, s[fit], a[fit], n[fit],
                                                  self.adapt_params, self.clip).items()}
        else:
            cand = dict(self.theta_star)
        ll = torch.tensor([self._log_lik(p, s[sc], a[sc], n[sc]) for p in [*self.tasks, cand]], dtype=torch.float64)
        post = task_posterior(ll, self.counts, self.alpha)
        L = len(self.tasks)
        if L == 0 or post[L] > post[:L].max():
            if L < self.max_tasks:
                self.tasks.append(cand)
                self.counts = torch.cat([self.counts, torch.zeros(1, dtype=torch.float64)])
            else:
                self.refused += 1
                post = post[:L] / post[:L].sum()
        else:
            post = post[:L] / post[:L].sum()
        # M-step: every task, weighted by its posterior
        for i, w in enumerate(post.tolist()):
            if w < 1e-6:
                continue  # a negligible step; skipping it saves a backward pass per idle task
            g = self._grad(self.tasks[i], s, a, n)
            self.tasks[i] = {k: (v - self.lr * w * g[k]).detach() for k, v in self.tasks[i].items()}
        self.counts = self.counts + post
        task = int(torch.argmax(post))
        return dict(self.tasks[task]), {"posterior": [float(p) for p in post], "task": task,
                                        "tasks_created": len(self.tasks), "refused_tasks": self.refused}

    def checkpoint(self) -> dict[str, Any]:
        return {**super().checkpoint(), "psi": {k: v.clone() for k, v in self.psi.items()}, "mole_lr": self.lr,
                "alpha": self.alpha, "max_tasks": self.max_tasks, "score": self.score,
                "adapt_params": self.adapt_params, "clip": self.clip}

    @classmethod
    def from_checkpoint(cls, ck: dict[str, Any]) -> MoleAdapter:
        """From a MOLe checkpoint, or a GrBAL one (its θ* and ψ are the prior)."""
        if "psi" not in ck:
            raise ValueError("MOLe needs a meta-learned prior: the checkpoint has no step size psi (train GrBAL first)")
        return cls(AdaptiveMLP.from_checkpoint(ck["model"]), ck["psi"], window=ck["window"],
                   lr=ck.get("mole_lr", 0.01), alpha=ck.get("alpha", 1.0), max_tasks=ck.get("max_tasks", 32),
                   score=ck.get("score"), adapt_params=ck.get("adapt_params"), clip=ck.get("clip"))
