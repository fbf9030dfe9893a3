"""Neural-network dynamics: an MLP (or a bootstrap ensemble of MLPs) predicting Δs.

Model (Nagabandi et al.; thesis defaults): for each ensemble member ``e``

    x  = ([s_t, a_t] - μ_x) / σ_x                      input normalization
    y  = MLP_e(x)          2 hidden layers of 500, ReLU
    ŝ_{t+1} = s_t + σ_Δ · y + μ_Δ                       output de-normalization

trained with Adam (lr 1e-3) on the MSE between ``y`` and the normalized true delta
``(Δs - μ_Δ) / σ_Δ``. Optional Gaussian noise of std ``input_noise_std`` (in normalized
units) is added to ``x`` during training only. Optional supervised-learning noise
``noise_to_signal`` (google-research/pddm's ``noiseToSignal``): Gaussian noise of std
``noise_to_signal`` × each channel's standard deviation over the training data, added to the
state part of the inputs and to the delta targets (not to the actions), drawn afresh for every
batch, training only. The reference scales it by each channel's *mean* (frame-dependent: see
docs/baoding.md); here by the spread, so it is the same whatever the world frame's origin.

Ensembles are ONE batched computation: layer ``l`` has weights ``[E, in, out]`` and biases
``[E, 1, out]`` applied with ``torch.baddbmm``; there is no Python loop over members. Each
member starts from its own random init and, when ``bootstrap`` is on (default for E > 1),
trains on its own bootstrap resample (N indices drawn with replacement) of the data.

Warm start: calling :meth:`EnsembleDynamics.fit` again continues from the current weights
and optimizer. Normalization rule (``norm_update``):

* ``"refit"`` (default): statistics are recomputed from the dataset passed to this ``fit``
  (in the MBRL loop: the aggregated dataset) and the first and last layers are rescaled so
  the network computes exactly the same function as before the update; training then
  continues in the new normalized coordinates. Adam's moment estimates are reset because
  they refer to the old coordinates.
* ``"freeze"``: statistics from the first ``fit`` are kept forever.

Inference (:meth:`predict` without autograd) uses a fused copy of the weights with the
normalization folded into the first and last layers, splits the batch into equal chunks so
the batched matmul keeps every thread busy (a fixed rule, or the split measured fastest on
this machine by :meth:`EnsembleDynamics.tune_inference`), and optionally runs in bfloat16
(``inference_dtype``; see :func:`cpu_bf16_support`). Training is always float32.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import nn

from hilstack.learning.datasets import Episode, NormStats, TransitionDataset
from hilstack.learning.progress import progress as progress_output

__all__ = ["EnsembleDynamics", "cpu_bf16_support", "h_step_windows", "h_step_error"]

_CHECKPOINT_FORMAT = "hilstack.EnsembleDynamics"
_CHECKPOINT_VERSION = 1
_IGNORED_STD = 1e12


def cpu_bf16_support(cpuinfo: str | Path = "/proc/cpuinfo") -> str | None:
    """Which native bfloat16 matmul the CPU has: ``"amx"``, ``"avx512"`` or ``None``.

    Reads the ``flags`` line of ``/proc/cpuinfo`` (``amx_bf16``, ``avx512_bf16``). Returns
    ``None`` when the file cannot be read (non-Linux) so callers fall back to float32.
    """
    try:
        text = Path(cpuinfo).read_text()
    except OSError:
        return None
    flags: set[str] = set()
    for line in text.splitlines():
        if line.startswith("flags"):
            flags.update(line.split(":", 1)[1].split())
    if "amx_bf16" in flags:
        return "amx"
    if "avx512_bf16" in flags:
        return "avx512"
    return None


AUTO_BF16_MIN_SPEEDUP = 1.25  # "auto" takes bf16 only when it measured at least this much faster


def _resolve_inference_dtype(choice: str, measure) -> torch.dtype:
    """``"fp32"`` / ``"bf16"`` / ``"auto"``.

    ``"auto"`` measures: on a CPU with native bf16 (:func:`cpu_bf16_support`), ``measure()``
    (:meth:`EnsembleDynamics.measure_dtypes`: the model's own inference in both precisions,
    interleaved) must find bf16 at least ``AUTO_BF16_MIN_SPEEDUP`` times faster, else fp32. A
    rule by CPU flag was wrong both ways on these machines: on one AVX512-BF16 CPU without AMX
    bf16 batched matmuls measured *slower* than fp32; on another (AMD EPYC, ``avx512_bf16``, no
    AMX) the Baoding plan (K = 700, one thread) measured 2.5-2.7x *faster*, and with AMX the
    platform notes measured 2.8x (docs/baoding.md, "Three seeds, bf16, and what keeps the pair
    in the hand"). Without native support it is fp32 with no measurement (emulated bf16 is slow).
    ``"bf16"`` forces bfloat16 whenever the CPU has any native bf16 support, else fp32.
    """
    if choice in ("fp32", "float32"):
        return torch.float32
    if choice not in ("bf16", "bfloat16", "auto"):
        raise ValueError(f"inference_dtype must be 'fp32', 'bf16' or 'auto', got {choice!r}")
    if not cpu_bf16_support():
        return torch.float32
    if choice == "auto":
        return torch.bfloat16 if measure()["speedup"] >= AUTO_BF16_MIN_SPEEDUP else torch.float32
    return torch.bfloat16


def _relu_(h: torch.Tensor) -> torch.Tensor:
    """In-place ReLU. For bfloat16, on the bits seen as int16: a bf16 number is sign and
    magnitude, so ``max(x, 0)`` keeps every number with the sign bit clear and maps every
    negative (and −0) to +0, which is ``clamp_min(0)`` on the int16 view. Exact for every
    non-NaN value (a NaN with the sign bit set becomes 0, where torch keeps NaN), and measured
    3.4x faster than bf16 ``relu_`` on a [12, 175, 500] planning batch (one thread, AMX CPU),
    where torch's bf16 element-wise kernels convert to fp32 and back."""
    if h.dtype == torch.bfloat16:
        h.view(torch.int16).clamp_min_(0)
        return h
    return h.relu_()


# -- H-step open-loop validation (thesis Eqn 2.2) ---------------------------------------------
def h_step_windows(
    episodes: Sequence[Episode], horizon: int, max_starts: int | None = 1024, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All start points ``t`` with ``t + H <= T`` of every episode, as batched windows.

    Returns ``(start [P,S], actions [P,H,A], truth [P,H,S])`` where ``truth[p, h-1]`` is the
    logged state ``h`` steps after the start. At most ``max_starts`` start points are kept
    (a seeded random subset) so validation stays cheap on long logs.
    """
    starts, acts, truth = [], [], []
    for ep in episodes:
        T = len(ep)
        if T < horizon:
            continue
        idx = np.arange(T - horizon + 1)
        win = idx[:, None] + np.arange(horizon)[None, :]
        starts.append(ep.states[idx])
        acts.append(ep.actions[win])
        truth.append(ep.states[win + 1])
    if not starts:
        raise ValueError(f"no episode is long enough for a {horizon}-step validation window")
    s, a, y = np.concatenate(starts), np.concatenate(acts), np.concatenate(truth)
    if max_starts is not None and s.shape[0] > max_starts:
        keep = np.sort(np.random.default_rng(seed).choice(s.shape[0], max_starts, replace=False))
        s, a, y = s[keep], a[keep], y[keep]
    return s, a, y


class EnsembleDynamics(nn.Module):
    """Bootstrap ensemble of MLPs predicting the state delta. See the module docstring.

    Args:
        state_dim, action_dim: S and A.
        ensemble: number of members E (1 = a single model, no bootstrap).
        hidden: hidden layer widths.
        lr, weight_decay: Adam settings.
        input_noise_std: std of Gaussian noise added to the normalized inputs while training.
        loss_weights: per state channel weight of the normalized delta's squared error in the
            training loss (default: all 1); scaled to mean 1, so the loss stays comparable.
        noise_to_signal: while training, Gaussian noise of std ``noise_to_signal`` × each
            channel's std over the training data is added to the state inputs and the delta
            targets (not the actions); 0 = none (see the module docstring).
        bootstrap: resample training data per member; default ``ensemble > 1``.
        norm_update: ``"refit"`` or ``"freeze"`` (see module docstring).
        inference_dtype: ``"fp32"`` (default), ``"bf16"`` or ``"auto"``.
        state_names, action_names, state_units, action_units: carried in checkpoints.
        seed: seeds the weight init and the training data order.
    """

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        ensemble: int = 1,
        hidden: Sequence[int] = (500, 500),
        *,
        lr: float = 1e-3,
        weight_decay: float = 0.0,
        input_noise_std: float = 0.0,
        loss_weights: Sequence[float] | None = None,
        noise_to_signal: float = 0.0,
        bootstrap: bool | None = None,
        norm_update: str = "refit",
        inference_dtype: str = "fp32",
        state_names: Sequence[str] | None = None,
        action_names: Sequence[str] | None = None,
        state_units: Sequence[str] | None = None,
        action_units: Sequence[str] | None = None,
        seed: int | None = 0,
    ) -> None:
        super().__init__()
        if norm_update not in ("refit", "freeze"):
            raise ValueError(f"norm_update must be 'refit' or 'freeze', got {norm_update!r}")
        if loss_weights is not None:
            lw = np.asarray(loss_weights, dtype=float)
            if lw.shape != (int(state_dim),) or not np.all(np.isfinite(lw)) or np.any(lw < 0) or lw.sum() <= 0:
                raise ValueError(f"loss_weights must be {int(state_dim)} finite weights >= 0 (not all 0), "
                                 f"got {list(loss_weights)}")
        if not (math.isfinite(noise_to_signal) and 0.0 <= noise_to_signal <= 1.0):
            raise ValueError(f"noise_to_signal must be in [0, 1], got {noise_to_signal}")
        self.config = dict(
            state_dim=int(state_dim),
            action_dim=int(action_dim),
            ensemble=int(ensemble),
            hidden=[int(h) for h in hidden],
            lr=float(lr),
            weight_decay=float(weight_decay),
            input_noise_std=float(input_noise_std),
            loss_weights=None if loss_weights is None else [float(w) for w in loss_weights],
            noise_to_signal=float(noise_to_signal),
            bootstrap=bool(ensemble > 1) if bootstrap is None else bool(bootstrap),
            norm_update=norm_update,
            inference_dtype=inference_dtype,
            seed=seed,
        )
        self.state_names = list(state_names) if state_names is not None else None
        self.action_names = list(action_names) if action_names is not None else None
        self.state_units = list(state_units) if state_units is not None else None
        self.action_units = list(action_units) if action_units is not None else None
        S, A, E = self.state_dim, self.action_dim, self.ensemble
        sizes = [S + A, *self.config["hidden"], S]
        gen = torch.Generator().manual_seed(0 if seed is None else int(seed))
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:], strict=True):
            # nn.Linear's default init, drawn independently for every member
            bound = 1.0 / math.sqrt(fan_in)
            w = (torch.rand(E, fan_in, fan_out, generator=gen) * 2 - 1) * bound
            b = (torch.rand(E, 1, fan_out, generator=gen) * 2 - 1) * bound
            self.weights.append(nn.Parameter(w))
            self.biases.append(nn.Parameter(b))
        # normalization statistics (identity until the first fit)
        self.register_buffer("input_mean", torch.zeros(S + A))
        self.register_buffer("input_std", torch.ones(S + A))
        self.register_buffer("delta_mean", torch.zeros(S))
        self.register_buffer("delta_std", torch.ones(S))
        self.register_buffer("state_std", torch.ones(S))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))
        self.history: list[dict] = []
        self._optimizer: torch.optim.Optimizer | None = None
        self._gen = torch.Generator().manual_seed(1 + (0 if seed is None else int(seed)))
        self._fast: dict | None = None  # fused inference weights, rebuilt lazily
        self._chunks_pinned: dict[int, int] = {}  # batch size -> chunk count (tune_inference)
        self.dtype_measurement: dict | None = None  # "auto"'s timing (measure_dtypes), if it ran
        self._inference_dtype = torch.float32  # measure_dtypes restores it: it must exist first
        self._inference_dtype = _resolve_inference_dtype(inference_dtype, self.measure_dtypes)

    # -- sizes ---------------------------------------------------------------------------
    @property
    def state_dim(self) -> int:
        return self.config["state_dim"]

    @property
    def action_dim(self) -> int:
        return self.config["action_dim"]

    @property
    def ensemble(self) -> int:
        return self.config["ensemble"]

    @property
    def inference_dtype(self) -> torch.dtype:
        return self._inference_dtype

    def set_inference_dtype(self, choice: str) -> torch.dtype:
        """Switch inference precision (``"fp32"``, ``"bf16"``, ``"auto"``); returns the dtype used."""
        self._inference_dtype = _resolve_inference_dtype(choice, self.measure_dtypes)
        self.config["inference_dtype"] = choice
        self._fast = None
        self._chunks_pinned.clear()  # measured for the old precision
        return self._inference_dtype

    # -- differentiable forward in normalized coordinates -----------------------------------
    def forward_normalized(self, x: torch.Tensor) -> torch.Tensor:
        """``[E, B, S+A]`` normalized inputs → ``[E, B, S]`` normalized deltas."""
        h = x
        n = len(self.weights)
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            h = torch.baddbmm(b, h, w)
            if i < n - 1:
                h = torch.relu(h)
        return h

    def _as_ensemble(self, x: torch.Tensor, name: str) -> torch.Tensor:
        if x.dim() == 2:
            return x.unsqueeze(0).expand(self.ensemble, -1, -1)
        if x.dim() == 3 and x.shape[0] == self.ensemble:
            return x
        raise ValueError(f"{name} must be [B,dim] or [E={self.ensemble},B,dim], got {tuple(x.shape)}")

    def _predict_diff(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Differentiable prediction: same contract as :meth:`predict`."""
        s = self._as_ensemble(state, "state")
        a = self._as_ensemble(action, "action")
        x = (torch.cat([s, a], dim=-1) - self.input_mean) / self.input_std
        y = self.forward_normalized(x)
        return s + y * self.delta_std + self.delta_mean

    # -- fast inference ------------------------------------------------------------------
    def _fused(self) -> dict:
        """Weights with normalization folded in, split into state/action parts, cast once."""
        if self._fast is not None:
            return self._fast
        S = self.state_dim
        with torch.no_grad():
            ws = [w.detach() for w in self.weights]
            bs = [b.detach() for b in self.biases]
            dt = self._inference_dtype
            # first layer: ((x - μ)/σ) W + b = x (W/σ) + (b - (μ/σ) W) in fp32. Not in bf16: its
            # 8-bit mantissa would round a raw input far from zero (a ball at 1 m: 4-8 mm
            # steps) before the normalisation; there the inputs are normalised in fp32 first
            fold = dt == torch.float32
            w0 = ws[0] / self.input_std[None, :, None] if fold else ws[0]
            b0 = (bs[0] - torch.einsum("i,eio->eo", self.input_mean / self.input_std, ws[0]).unsqueeze(1)
                  if fold else bs[0])
            # last layer: (h W + b) σ_Δ + μ_Δ
            wl = ws[-1] * self.delta_std
            bl = bs[-1] * self.delta_std + self.delta_mean
            ws = [w0, *ws[1:-1], wl] if len(ws) > 1 else [w0 * self.delta_std]
            bs = [b0, *bs[1:-1], bl] if len(bs) > 1 else [b0 * self.delta_std + self.delta_mean]
            self._fast = {
                "normalize": None if fold else (self.input_mean[:S].clone(), self.input_std[:S].clone(),
                                                self.input_mean[S:].clone(), self.input_std[S:].clone()),
                "w_s": ws[0][:, :S].to(dt).contiguous(),
                "w_a": ws[0][:, S:].to(dt).contiguous(),
                "ws": [w.to(dt).contiguous() for w in ws[1:]],
                "bs": [b.to(dt).contiguous() for b in bs],
                "chunked": {},
            }
        return self._fast

    def _chunk_weights(self, k: int) -> dict:
        """Weights repeated ``k`` times along the member axis (member-major), cached."""
        fast = self._fused()
        if k not in fast["chunked"]:
            rep = lambda t: t.repeat_interleave(k, dim=0).contiguous()  # noqa: E731
            fast["chunked"][k] = {
                "w_s": rep(fast["w_s"]),
                "w_a": rep(fast["w_a"]),
                "ws": [rep(w) for w in fast["ws"]],
                "bs": [rep(b) for b in fast["bs"]],
            }
        return fast["chunked"][k]

    @staticmethod
    def _chunks_for(batch: int) -> int:
        # A batched matmul parallelizes over its batch axis; E=3 members on 2 threads leaves one
        # idle a third of the time. Splitting the samples into k equal chunks (a free view)
        # gives E*k balanced work items (measured 4.8 -> 3.5 ms per 500x500 layer, E=3, B=700).
        for k in (4, 2):
            if batch % k == 0 and batch // k >= 64:
                return k
        return 1

    def tune_inference(self, batch: int, candidates: Sequence[int] = (1, 2, 4), reps: int = 5) -> int:
        """Measure which chunk count is fastest for ``batch`` inputs per member on this machine
        and use it from now on (for this batch size; not saved in checkpoints).

        The default split (:meth:`_chunks_for`, 4 chunks at the planner's 700 samples) was
        measured on an AVX-512 machine; on an AVX2 machine the same split was ~1.4x slower
        than one chunk (``hil bench plan``, ``baoding.levers.tuned_chunks``). The result is
        the same function whatever the choice (only the summation order of the batched
        matmuls changes), so tuning can only change speed. Times ``reps`` calls per
        candidate, interleaved so load from other processes hits all alike, after one
        warm-up round; picks the lowest median. Returns the chunk count chosen.
        """
        valid = [int(k) for k in candidates if int(k) >= 1 and batch % int(k) == 0]
        if not valid:
            raise ValueError(f"no chunk count in {list(candidates)} divides batch={batch}")
        s = torch.zeros(self.ensemble, batch, self.state_dim)
        a = torch.zeros(batch, self.action_dim)
        times: dict[int, list[float]] = {k: [] for k in valid}
        with torch.inference_mode():
            for r in range(reps + 1):
                for k in valid:
                    self._chunks_pinned[batch] = k
                    t0 = time.perf_counter()
                    self.predict(s, a)
                    if r:  # round 0 warms up (and builds the chunked weights)
                        times[k].append(time.perf_counter() - t0)
        best = min(valid, key=lambda k: float(np.median(times[k])))
        self._chunks_pinned[batch] = best
        return best

    def measure_dtypes(self, batch: int = 700, reps: int = 7) -> dict:
        """Time :meth:`predict` on ``batch`` inputs per member in fp32 and in bf16 (``reps`` calls
        each after a warm-up, interleaved so load from other processes hits both alike; the
        median): ``{"batch", "fp32_ms", "bf16_ms", "speedup"}`` (fp32 / bf16), also kept in
        :attr:`dtype_measurement`. The precision in use is restored. 700 is the Baoding
        planner's K; the ratio, not the times, decides (``"auto"``)."""
        keep, keep_pinned = self._inference_dtype, dict(self._chunks_pinned)
        s, a = torch.zeros(self.ensemble, batch, self.state_dim), torch.zeros(batch, self.action_dim)
        times: dict[torch.dtype, list[float]] = {torch.float32: [], torch.bfloat16: []}
        fused: dict[torch.dtype, dict] = {}
        try:
            with torch.inference_mode():
                for r in range(reps + 1):
                    for dt in times:
                        self._inference_dtype, self._fast = dt, fused.get(dt)
                        t0 = time.perf_counter()
                        self.predict(s, a)
                        fused[dt] = self._fast
                        if r:  # round 0 warms up (and casts the weights)
                            times[dt].append(time.perf_counter() - t0)
        finally:
            self._inference_dtype, self._fast = keep, None
            self._chunks_pinned = keep_pinned
        f, b = (1e3 * float(np.median(times[d])) for d in (torch.float32, torch.bfloat16))
        self.dtype_measurement = {"batch": int(batch), "fp32_ms": f, "bf16_ms": b, "speedup": f / b}
        return self.dtype_measurement

    def predict(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Predict the next state.

        Args:
            state: ``[B, S]`` (the same state for every member) or ``[E, B, S]``.
            action: ``[B, A]`` or ``[E, B, A]``.
        Returns:
            ``[E, B, S]`` float32 next states (always with the member axis).

        With autograd enabled this is the differentiable :meth:`forward`; under
        ``torch.no_grad``/``torch.inference_mode`` (as planners call it) it runs the fused
        inference path in :attr:`inference_dtype`.
        """
        if torch.is_grad_enabled():
            return self._predict_diff(state, action)
        E, S = self.ensemble, self.state_dim
        B = state.shape[-2]
        k = self._chunks_pinned.get(B) or self._chunks_for(B)
        w = self._chunk_weights(k)
        dt = self._inference_dtype
        s3 = self._as_ensemble(state, "state")
        a3 = self._as_ensemble(action, "action")
        norm = self._fused()["normalize"]
        s_in, a_in = (s3, a3) if norm is None else ((s3 - norm[0]) / norm[1], (a3 - norm[2]) / norm[3])
        # [E, B, .] -> [E*k, B/k, .]: a view when contiguous, a small copy when broadcast
        s_c = s_in.reshape(E * k, B // k, S).to(dt)
        a_c = a_in.reshape(E * k, B // k, a3.shape[-1]).to(dt)
        h = torch.baddbmm(w["bs"][0], s_c, w["w_s"])
        h.baddbmm_(a_c, w["w_a"])
        for wi, bi in zip(w["ws"], w["bs"][1:], strict=True):
            h = torch.baddbmm(bi, _relu_(h), wi)
        delta = h.reshape(E, B, S)
        if dt != torch.float32:
            delta = delta.float()
        return s3 + delta

    def forward(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``model(state, action)`` is :meth:`predict`."""
        return self.predict(state, action)

    def dynamics(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Alias of :meth:`predict` with the planner's ``dynamics(state, action)`` signature."""
        return self.predict(state, action)

    # -- normalization ---------------------------------------------------------------------
    def ignore_inputs(self, state_channels: Sequence[int]) -> None:
        """Make the model blind to these state channels as inputs (they are still predicted).

        E.g. planar position on a robot whose dynamics do not depend on where it is: the
        learned model is then translation invariant and data from one part of the arena
        serves everywhere. Implemented through the input normalization (std → 1e12), so
        the fused inference path and checkpoints need nothing special. Call before ``fit``.
        """
        idx = sorted({int(i) for i in state_channels})
        if any(i < 0 or i >= self.state_dim for i in idx):
            raise ValueError(f"state channel index out of range 0..{self.state_dim - 1}: {idx}")
        self.config["ignore_inputs"] = idx
        with torch.no_grad():
            self.input_mean[idx] = 0.0
            self.input_std[idx] = _IGNORED_STD
        self._fast = None

    def _set_stats(self, st: NormStats) -> None:
        """Install new statistics, rescaling the first/last layer so the function is unchanged."""
        t = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
        mu_x, sd_x, mu_d, sd_d = t(st.input_mean), t(st.input_std), t(st.delta_mean), t(st.delta_std)
        ignored = self.config.get("ignore_inputs") or []
        if ignored:
            # an ignored input is normalized to ~0 whatever its value (see ignore_inputs)
            mu_x[ignored] = 0.0
            sd_x[ignored] = _IGNORED_STD
        with torch.no_grad():
            if bool(self.fitted):
                w0, b0 = self.weights[0], self.biases[0]
                # ((x-μo)/σo) W = ((x-μn)/σn) (σn/σo) W + ((μn-μo)/σo) W
                shift = torch.einsum("i,eio->eo", (mu_x - self.input_mean) / self.input_std, w0).unsqueeze(1)
                b0.add_(shift)
                w0.mul_((sd_x / self.input_std)[None, :, None])
                wl, bl = self.weights[-1], self.biases[-1]
                # y_o σo + μo = y_n σn + μn  =>  y_n = (y_o σo + μo - μn) / σn
                wl.mul_(self.delta_std / sd_d)
                bl.mul_(self.delta_std).add_(self.delta_mean - mu_d).div_(sd_d)
            self.input_mean.copy_(mu_x)
            self.input_std.copy_(sd_x)
            self.delta_mean.copy_(mu_d)
            self.delta_std.copy_(sd_d)
            self.state_std.copy_(t(st.state_std))
            self.fitted.fill_(True)
        self._fast = None

    # -- training --------------------------------------------------------------------------
    def fit(
        self,
        dataset: TransitionDataset | Sequence[Episode],
        epochs: int = 50,
        batch_size: int = 512,
        progress: bool = True,
        val: TransitionDataset | Sequence[Episode] | None = None,
        horizon: int = 10,
        max_val_starts: int = 1024,
    ) -> list[dict]:
        """Train (or continue training) on ``dataset``.

        Args:
            dataset: training transitions (episodes are wrapped in a TransitionDataset).
            epochs: passes over the (per-member bootstrap) data.
            batch_size: transitions per member per gradient step.
            progress: show progress with the latest losses (a tqdm bar on a terminal, lines in a log).
            val: held-out episodes; when given, every epoch records the one-step and the
                ``horizon``-step open-loop validation error (:func:`h_step_error`); H is
                shortened to the longest validation episode when all are shorter.
            horizon: H of the open-loop validation error.
            max_val_starts: cap on validation start points.
        Returns:
            the history entries of this call (also appended to :attr:`history`); each has
            ``epoch, train_loss, time_s`` and, with ``val``, ``val_1step``, ``val_h``,
            ``val_h_raw`` and ``horizon``.
        """
        if not isinstance(dataset, TransitionDataset):
            dataset = TransitionDataset(dataset)
        if val is not None and not isinstance(val, TransitionDataset):
            val = TransitionDataset(val)
        if (dataset.state_dim, dataset.action_dim) != (self.state_dim, self.action_dim):
            raise ValueError(
                f"dataset has S={dataset.state_dim}, A={dataset.action_dim}; model expects "
                f"S={self.state_dim}, A={self.action_dim}"
            )
        for attr in ("state_names", "action_names", "state_units", "action_units"):
            if getattr(self, attr) is None and getattr(dataset, attr) is not None:
                setattr(self, attr, list(getattr(dataset, attr)))
        if not bool(self.fitted) or self.config["norm_update"] == "refit":
            renorm = bool(self.fitted)
            self._set_stats(dataset.stats())
            if renorm and self._optimizer is not None:
                self._optimizer.state.clear()  # moments refer to the old coordinates
        if self._optimizer is None:
            self._optimizer = torch.optim.Adam(
                self.parameters(), lr=self.config["lr"], weight_decay=self.config["weight_decay"]
            )
        opt = self._optimizer
        E, N = self.ensemble, len(dataset)
        x_all = torch.from_numpy(np.concatenate([dataset.states, dataset.actions], axis=1))
        x_all = (x_all - self.input_mean) / self.input_std
        y_all = (torch.from_numpy(dataset.deltas) - self.delta_mean) / self.delta_std
        if self.config["bootstrap"]:
            boot = torch.randint(0, N, (E, N), generator=self._gen)
        else:
            boot = torch.arange(N).expand(E, N)
        windows = None
        if val is not None:
            # episodes that end early (a dropped object) can all be shorter than H: validate
            # over the longest window they hold; each entry's ``horizon`` says which
            horizon = min(horizon, max(len(e) for e in val.episodes))
            windows = h_step_windows(val.episodes, horizon, max_val_starts)
        noise = self.config["input_noise_std"]
        w_out = self.loss_weight_tensor()
        x_noise, y_noise = self._train_noise_scales(dataset)
        start_epoch = self.history[-1]["epoch"] + 1 if self.history else 0
        entries: list[dict] = []
        bar = None
        if progress:
            bar = progress_output(total=epochs, desc="fit")  # tqdm on a terminal, plain lines in a log
        n_batches = max(1, math.ceil(N / batch_size))
        for ep in range(epochs):
            t0 = time.perf_counter()
            self.train()
            # each member sees its own bootstrap sample in its own order
            perm = torch.argsort(torch.rand(E, N, generator=self._gen), dim=1)
            order = torch.gather(boot, 1, perm)
            total = 0.0
            for bi in range(n_batches):
                idx = order[:, bi * batch_size : (bi + 1) * batch_size]  # [E, b]
                xb, yb = x_all[idx], y_all[idx]  # [E, b, S+A], [E, b, S]
                if noise > 0:
                    xb = xb + noise * torch.randn(xb.shape, generator=self._gen)
                if x_noise is not None:
                    xb, yb = self._noisy_batch(xb, yb, x_noise, y_noise)
                pred = self.forward_normalized(xb)
                # sum over members of each member's mean loss: members train independently
                loss = (((pred - yb) ** 2) * w_out).mean(dim=(1, 2)).sum()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                total += loss.item() / E
            self._fast = None
            entry = {"epoch": start_epoch + ep, "train_loss": total / n_batches}
            if windows is not None:
                entry.update(self.evaluate(val, horizon=horizon, windows=windows))
            entry["time_s"] = time.perf_counter() - t0
            entries.append(entry)
            self.history.append(entry)
            if bar is not None:
                # postfix first: a plain-line log writes its line in update()
                bar.set_postfix({k: f"{v:.4g}" for k, v in entry.items() if k in ("train_loss", "val_h")})
                bar.update(1)
        if bar is not None:
            bar.close()
        self.eval()
        return entries

    def loss_weight_tensor(self) -> torch.Tensor:
        """``[S]`` training weights per state channel (``loss_weights`` scaled to mean 1; ones)."""
        lw = self.config.get("loss_weights")
        if lw is None:
            return torch.ones(self.state_dim)
        w = torch.as_tensor(lw, dtype=torch.float32)
        return w * (len(w) / w.sum())
    def _train_noise_scales(self, dataset: TransitionDataset) -> tuple[torch.Tensor, torch.Tensor] | tuple[None, None]:
        """Per-channel std of the ``noise_to_signal`` noise in normalized units: ``[S+A]`` for
        the inputs (0 on the actions) and ``[S]`` for the targets; ``(None, None)`` when off.
        ``r · std_raw / σ``: r on an ordinary channel, 0 on a constant one (its σ is 1, its
        spread 0), ~0 on an ignored one (σ = 1e12)."""
        r = self.config["noise_to_signal"]
        if r <= 0:
            return None, None
        sd_s = torch.from_numpy(np.asarray(dataset.states, dtype=np.float64).std(0)).float()
        sd_d = torch.from_numpy(np.asarray(dataset.deltas, dtype=np.float64).std(0)).float()
        x = torch.zeros(self.state_dim + self.action_dim)
        x[: self.state_dim] = r * sd_s / self.input_std[: self.state_dim]
        return x, r * sd_d / self.delta_std

    def _noisy_batch(self, xb: torch.Tensor, yb: torch.Tensor, x_noise: torch.Tensor,
                     y_noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A training batch (normalized) with the ``noise_to_signal`` noise of per-channel std
        ``x_noise`` / ``y_noise`` (:meth:`_train_noise_scales`) added."""
        return (xb + x_noise * torch.randn(xb.shape, generator=self._gen),
                yb + y_noise * torch.randn(yb.shape, generator=self._gen))

    # -- validation ------------------------------------------------------------------------
    def evaluate(
        self,
        val: TransitionDataset | Sequence[Episode],
        horizon: int = 10,
        windows: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> dict:
        """One-step and H-step validation errors (see :func:`h_step_error`)."""
        if not isinstance(val, TransitionDataset):
            val = TransitionDataset(val)
        with torch.inference_mode():
            x = (torch.from_numpy(np.concatenate([val.states, val.actions], 1)) - self.input_mean) / self.input_std
            y = (torch.from_numpy(val.deltas) - self.delta_mean) / self.delta_std
            pred = self.forward_normalized(x.unsqueeze(0).expand(self.ensemble, -1, -1))
            one = float(((pred - y) ** 2).mean())
        if windows is None:
            windows = h_step_windows(val.episodes, horizon)
        h_norm, h_raw = h_step_error(self, *windows)
        return {"val_1step": one, "val_h": h_norm, "val_h_raw": h_raw, "horizon": horizon}

    # -- checkpoints -----------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """``torch.save`` of a plain dict: config, names/units, weights, normalization, history."""
        torch.save(
            {
                "format": _CHECKPOINT_FORMAT,
                "version": _CHECKPOINT_VERSION,
                "config": dict(self.config),
                "state_names": self.state_names,
                "action_names": self.action_names,
                "state_units": self.state_units,
                "action_units": self.action_units,
                "state_dict": {k: v.detach().clone() for k, v in self.state_dict().items()},
                "history": list(self.history),
            },
            Path(path),
        )

    @classmethod
    def load(cls, path: str | Path) -> EnsembleDynamics:
        """Rebuild a model saved by :meth:`save` (weights-only unpickling: safe to load)."""
        ckpt = torch.load(Path(path), map_location="cpu", weights_only=True)
        if ckpt.get("format") != _CHECKPOINT_FORMAT:
            raise ValueError(f"{path}: not an EnsembleDynamics checkpoint (format={ckpt.get('format')!r})")
        cfg = dict(ckpt["config"])
        ignored = cfg.pop("ignore_inputs", None)
        # keys set by wrappers (e.g. body_frame) are carried, not constructor arguments
        import inspect

        init_args = set(inspect.signature(cls.__init__).parameters)
        extra = {k: cfg.pop(k) for k in list(cfg) if k not in init_args}
        model = cls(
            cfg.pop("state_dim"),
            cfg.pop("action_dim"),
            cfg.pop("ensemble"),
            cfg.pop("hidden"),
            state_names=ckpt["state_names"],
            action_names=ckpt["action_names"],
            state_units=ckpt["state_units"],
            action_units=ckpt["action_units"],
            **cfg,
        )
        model.config.update(extra)
        if ignored:
            model.ignore_inputs(ignored)
        model.load_state_dict(ckpt["state_dict"])
        model.history = list(ckpt["history"])
        model.eval()
        return model

    def load_state_dict(self, *args, **kwargs):  # noqa: D102 - invalidate the fused copy
        self._fast = None
        return super().load_state_dict(*args, **kwargs)


def h_step_error(
    model, start: np.ndarray, actions: np.ndarray, truth: np.ndarray,
    state_std: torch.Tensor | None = None, frame: Callable | None = None,
) -> tuple[float, float]:
    """Open-loop H-step prediction error (thesis Eqn 2.2).

    From each start state ``s_t`` the model is rolled out H steps replaying the logged actions
    (``ŝ_t = s_t``, ``ŝ_{t+h} = model(ŝ_{t+h-1}, a_{t+h-1})``), and

        E = 1/P Σ_t 1/H Σ_{h=1..H} ½ ‖ (s_{t+h} - ŝ_{t+h}) / σ_s ‖²

    averaged over ensemble members, with ``σ_s`` the per-channel state std of the training
    data (so channels in different units weigh alike). Returns ``(E_normalized, E_raw)``,
    ``E_raw`` being the same with ``σ_s = 1`` (in squared state units).

    Args:
        model: anything with ``predict(state, action) -> [E, P, S]``.
        start ``[P,S]``, actions ``[P,H,A]``, truth ``[P,H,S]``: from :func:`h_step_windows`.
        state_std: ``σ_s`` (default ``model.state_std``).
        frame: ``frame(states [..., P, S], start [P, S])``: compare predictions and truth in
            another frame, e.g. the body frame of each window's start state.
    """
    with torch.inference_mode():
        s = torch.from_numpy(np.ascontiguousarray(start)).float()
        a = torch.from_numpy(np.ascontiguousarray(actions)).float()
        y = torch.from_numpy(np.ascontiguousarray(truth)).float()
        std = model.state_std if state_std is None else state_std
        H = a.shape[1]
        err_n = torch.zeros(())
        err_r = torch.zeros(())
        cur = s
        for h in range(H):
            cur = model.predict(cur, a[:, h])  # [E, P, S]
            if frame is None:
                d = cur - y[:, h]
            else:
                d = frame(cur, s.expand_as(cur)) - frame(y[:, h], s)
            err_r = err_r + 0.5 * (d**2).sum(-1).mean()
            err_n = err_n + 0.5 * ((d / std) ** 2).sum(-1).mean()
        return float(err_n / H), float(err_r / H)
