"""SIDM: a System Invariant Dynamics Model shared by an expert and a novice system.

After Wang & Johnson (SIDM): each system ``k`` has its own encoder ``E_k(s, a) → z``
(latent of ``latent_dim``, 128 in the paper) and decoder ``D_k(h) → Δs``; one dynamics
network ``F(z) → h`` is shared. Training alternates

* ``pred_iters`` (100) prediction iterations: each minibatch comes from the expert with
  probability ``p_e`` and from the novice otherwise; the loss is the MSE of the decoded
  (normalised) state change, through that system's encoder and decoder and the shared F;
* ``match_iters`` (20) distribution-matching iterations: a discriminator on latents learns
  to tell expert latents (label 1) from novice ones (label 0), then the novice encoder is
  updated to make its latents look like the expert's (non-saturating GAN loss).

The baseline is the same network trained on novice data only (``p_e = 0``, no matching).

Sizes are options (``SidmConfig``). The paper's SIDM is 4 LSTM layers of 1024 over
sequences; ours is an MLP (``dyn_layers`` x ``width``) on single transitions, because the
state here is Markov (pose, velocities, crank phase, a local heightfield patch) and the CPU
budget is two shared cores (docs/transfer.md).

Units: inputs and targets are whatever the caller gives (SI for the VelociRoACH); each
system normalises its own inputs and targets (mean/std of its training data), so a
system's units never leak into the shared network.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from hilstack.learning.early_stopping import EarlyStopping


@dataclass(frozen=True)
class SidmConfig:
    """Sizes and the training schedule. Paper: latent 128, 4 x 1024 LSTM, 100/20 iterations."""

    latent_dim: int = 128
    width: int = 256
    enc_layers: int = 1  # hidden layers of each encoder / decoder
    dyn_layers: int = 2  # hidden layers of the shared dynamics network
    pred_iters: int = 100
    match_iters: int = 20
    p_e: float = 0.75  # paper: 0.75 similar pair, 0.5 dissimilar pair
    batch: int = 128
    lr: float = 1e-3
    disc_lr: float = 5e-4
    adv_weight: float = 0.1  # weight of the novice encoder's fooling loss
    max_rounds: int = 40  # one round = pred_iters + match_iters
    patience_rounds: int = 6  # early stopping on the novice test split
    test_fraction: float = 0.25  # paper: 75/25 train/test split
    warm_rounds: int = 0  # SIDM only: expert-only prediction rounds, then novice enc/dec := expert's
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.p_e <= 1.0:
            raise ValueError(f"SidmConfig.p_e must be in [0, 1], got {self.p_e}")
        if self.warm_rounds < 0:
            raise ValueError(f"SidmConfig.warm_rounds must be >= 0, got {self.warm_rounds}")
        for n in ("latent_dim", "width", "batch", "max_rounds"):
            if getattr(self, n) < 1:
                raise ValueError(f"SidmConfig.{n} must be >= 1, got {getattr(self, n)}")


def _mlp(n_in: int, n_out: int, width: int, layers: int) -> nn.Sequential:
    mods: list[nn.Module] = []
    d = n_in
    for _ in range(layers):
        mods += [nn.Linear(d, width), nn.SiLU()]
        d = width
    mods.append(nn.Linear(d, n_out))
    return nn.Sequential(*mods)


@dataclass
class ModelSamples:
    """One system's regression data for the SIDM: inputs ``x`` [N, n_in] (state features and
    action) and targets ``y`` [N, n_out] (state change over one control period), built from a
    system's transitions (hilstack.learning.datasets.Transitions) by a pairs module's
    feature map (roach_pairs, wheeled_pairs)."""

    x: np.ndarray
    y: np.ndarray

    def __post_init__(self) -> None:
        self.x = np.asarray(self.x, dtype=np.float32)
        self.y = np.asarray(self.y, dtype=np.float32)
        if self.x.ndim != 2 or self.y.ndim != 2 or len(self.x) != len(self.y):
            raise ValueError(f"ModelSamples: x {self.x.shape} and y {self.y.shape} must be 2-D with equal rows")
        if not (np.isfinite(self.x).all() and np.isfinite(self.y).all()):
            raise ValueError("ModelSamples: x or y contains NaN or inf")

    def __len__(self) -> int:
        return len(self.x)

    def subset(self, idx: np.ndarray) -> ModelSamples:
        return ModelSamples(self.x[idx], self.y[idx])


class _Norm(nn.Module):
    """Fixed affine normalisation from a system's training data (std floored at 1e-6)."""

    def __init__(self, data: np.ndarray):
        super().__init__()
        self.register_buffer("mu", torch.as_tensor(data.mean(0), dtype=torch.float32))
        self.register_buffer("sd", torch.as_tensor(np.maximum(data.std(0), 1e-6), dtype=torch.float32))


class Sidm(nn.Module):
    """Per-system encoders and decoders around one shared dynamics network."""

    def __init__(self, n_in: int, n_out: int, systems: tuple[str, ...], cfg: SidmConfig):
        super().__init__()
        self.cfg = cfg
        self.systems = systems
        self.enc = nn.ModuleDict({k: _mlp(n_in, cfg.latent_dim, cfg.width, cfg.enc_layers) for k in systems})
        self.dec = nn.ModuleDict({k: _mlp(cfg.latent_dim, n_out, cfg.width, cfg.enc_layers) for k in systems})
        self.dyn = _mlp(cfg.latent_dim, cfg.latent_dim, cfg.width, cfg.dyn_layers)
        self.xn = nn.ModuleDict()
        self.yn = nn.ModuleDict()

    def set_norm(self, system: str, data: ModelSamples) -> None:
        self.xn[system] = _Norm(data.x)
        self.yn[system] = _Norm(data.y)

    def encode(self, system: str, x: torch.Tensor) -> torch.Tensor:
        n = self.xn[system]
        return self.enc[system]((x - n.mu) / n.sd)

    def predict_norm(self, system: str, x: torch.Tensor) -> torch.Tensor:
        """The normalised state change for inputs ``x`` (raw units)."""
        return self.dec[system](self.dyn(self.encode(system, x)))

    @torch.no_grad()
    def predict(self, system: str, x: np.ndarray) -> np.ndarray:
        """State change in the caller's units for inputs ``x`` [N, n_in]."""
        n = self.yn[system]
        y = self.predict_norm(system, torch.as_tensor(np.asarray(x, np.float32))) * n.sd + n.mu
        return y.numpy()

    def loss(self, system: str, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        n = self.yn[system]
        return ((self.predict_norm(system, x) - (y - n.mu) / n.sd) ** 2).mean()


def discriminator(latent_dim: int, width: int = 128) -> nn.Sequential:
    """Logit of "this latent came from the expert"."""
    return _mlp(latent_dim, 1, width, 2)


def adversarial_step(model: Sidm, disc: nn.Module, opt_d: torch.optim.Optimizer, opt_enc: torch.optim.Optimizer,
                     xe: torch.Tensor, xn: torch.Tensor, adv_weight: float = 1.0,
                     expert: str = "expert", novice: str = "novice") -> tuple[float, float]:
    """One distribution-matching iteration: a discriminator step on detached latents (expert 1,
    novice 0), then a novice-encoder step on the non-saturating loss −log D(E_n(x)).
    Returns (discriminator loss, novice fooling loss)."""
    bce = nn.functional.binary_cross_entropy_with_logits
    ze = model.encode(expert, xe).detach()
    zn = model.encode(novice, xn)
    ld = bce(disc(ze), torch.ones(len(ze), 1)) + bce(disc(zn.detach()), torch.zeros(len(zn), 1))
    opt_d.zero_grad()
    ld.backward()
    opt_d.step()
    lg = bce(disc(zn), torch.ones(len(zn), 1))
    opt_enc.zero_grad()
    (adv_weight * lg).backward()
    opt_enc.step()
    return float(ld.detach()), float(lg.detach())


def split(data: ModelSamples, test_fraction: float, rng: np.random.Generator) -> tuple[ModelSamples, ModelSamples]:
    """Random train/test split (paper: 75/25) with at least one sample on each side."""
    idx = rng.permutation(len(data))
    n_test = min(max(1, int(round(test_fraction * len(data)))), len(data) - 1)
    return data.subset(idx[n_test:]), data.subset(idx[:n_test])


def train_sidm(novice: ModelSamples, cfg: SidmConfig, expert: ModelSamples | None = None,
               init: Sidm | None = None) -> Sidm:
    """Train SIDM (``expert`` given, ``p_e`` > 0) or the novice-only baseline
    (``expert`` None or ``p_e`` == 0: no expert batches and no matching). Early stopping on
    the novice test split; the best model is returned.

    ``init`` (novice-only training only): fine-tuning. The network starts from ``init``'s
    weights (its ``"novice"`` system: e.g. a model trained on the expert's data alone) instead
    of at random; the novice keeps its own input/target normalisation, as in the warm start."""
    if len(novice) < 2:
        raise ValueError(f"train_sidm: need at least 2 novice transitions, got {len(novice)}")
    use_expert = expert is not None and cfg.p_e > 0
    if init is not None and use_expert:
        raise ValueError("train_sidm: init (fine-tuning) is for the novice-only network, not with an expert")
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    n_train, n_test = split(novice, cfg.test_fraction, rng)
    systems = ("expert", "novice") if use_expert else ("novice",)
    model = Sidm(novice.x.shape[1], novice.y.shape[1], systems, cfg)
    model.set_norm("novice", n_train)
    if use_expert:
        model.set_norm("expert", expert)
    if init is not None:
        src = "novice" if "novice" in init.systems else init.systems[0]
        model.enc["novice"].load_state_dict(init.enc[src].state_dict())
        model.dec["novice"].load_state_dict(init.dec[src].state_dict())
        model.dyn.load_state_dict(init.dyn.state_dict())
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    disc = discriminator(cfg.latent_dim)
    opt_d = torch.optim.Adam(disc.parameters(), lr=cfg.disc_lr)
    opt_enc = torch.optim.Adam(model.enc["novice"].parameters(), lr=cfg.lr)
    data = {"novice": n_train, "expert": expert}
    tx, ty = torch.as_tensor(n_test.x), torch.as_tensor(n_test.y)

    def batch(system: str) -> tuple[torch.Tensor, torch.Tensor]:
        d = data[system]
        i = rng.integers(0, len(d), size=min(cfg.batch, len(d)))
        return torch.as_tensor(d.x[i]), torch.as_tensor(d.y[i])

    if use_expert and cfg.warm_rounds > 0:
        # warm start: the shared network and the expert's encoder/decoder learn the expert's
        # dynamics, then the novice starts from the expert's encoder/decoder (each system keeps
        # its own normalisation, so the copy maps standardised novice inputs like the expert's)
        model.train()
        for _ in range(cfg.warm_rounds * cfg.pred_iters):
            x, y = batch("expert")
            loss = model.loss("expert", x, y)
            opt.zero_grad()
            loss.backward()
            opt.step()
        model.enc["novice"].load_state_dict(model.enc["expert"].state_dict())
        model.dec["novice"].load_state_dict(model.dec["expert"].state_dict())
    es = EarlyStopping(model, patience=cfg.patience_rounds, min_delta=1e-6, keep_initial=True)
    for _ in range(cfg.max_rounds):
        model.train()
        for _ in range(cfg.pred_iters):
            system = "expert" if use_expert and rng.random() < cfg.p_e else "novice"
            x, y = batch(system)
            loss = model.loss(system, x, y)
            opt.zero_grad()
            loss.backward()
            opt.step()
        if use_expert:
            for _ in range(cfg.match_iters):
                adversarial_step(model, disc, opt_d, opt_enc, batch("expert")[0], batch("novice")[0], cfg.adv_weight)
        with torch.no_grad():
            test = float(model.loss("novice", tx, ty))
        if es.update(test):
            break
    es.restore()
    model.eval()
    return model


def validation_mse(model: Sidm, data: ModelSamples, system: str = "novice", scale: np.ndarray | None = None) -> float:
    """Mean squared error of the state change divided by ``scale`` per channel (default: the
    model's own target scale for ``system``, i.e. its training data's std). Give a fixed
    ``scale`` (e.g. the validation data's std) to compare models trained on different data."""
    with torch.no_grad():
        if scale is None:
            return float(model.loss(system, torch.as_tensor(data.x), torch.as_tensor(data.y)))
        sc = np.asarray(scale, np.float32)
        if sc.shape != (data.y.shape[1],) or not (np.isfinite(sc).all() and (sc > 0).all()):
            raise ValueError(f"validation_mse: scale must be {data.y.shape[1]} positive finite values")
        return float((((model.predict(system, data.x) - data.y) / sc) ** 2).mean())


def target_scale(data: ModelSamples) -> np.ndarray:
    """Per-channel std of the state change (floored at 1e-6): the fixed scale of the validation error."""
    return np.maximum(data.y.std(0), 1e-6).astype(np.float32)


def latent_mean_distance(model: Sidm, xe: np.ndarray, xn: np.ndarray) -> float:
    """‖mean E_e(xe) − mean E_n(xn)‖ / latent RMS: a cheap distance between latent distributions."""
    with torch.no_grad():
        ze = model.encode("expert", torch.as_tensor(np.asarray(xe, np.float32)))
        zn = model.encode("novice", torch.as_tensor(np.asarray(xn, np.float32)))
        scale = torch.cat([ze, zn]).std(0).pow(2).sum().sqrt().clamp_min(1e-9)
        return float((ze.mean(0) - zn.mean(0)).norm() / scale)


def data_multiplier(minutes: list[float], with_sidm: list[float], without_sidm: list[float]) -> dict:
    """Summary of ``data_multipliers``: the median of the sizes where the multiplier was
    interpolated (None if none was), and how many sizes fell beyond or below the grid."""
    per = data_multipliers(minutes, with_sidm, without_sidm)
    inside = [p["multiplier"] for p in per if p["where"] == "interpolated"]
    return {"median_interpolated": float(np.median(inside)) if inside else None,
            "interpolated": len(inside),
            "beyond_grid": sum(p["where"] == "beyond" for p in per),
            "below_grid": sum(p["where"] == "below" for p in per)}


def data_multipliers(minutes: list[float], with_sidm: list[float], without_sidm: list[float]) -> list[dict]:
    """How much more novice data the baseline needs to reach SIDM's error, at each size.

    For each size m_i, the baseline's error curve (made monotone by a running minimum,
    interpolated linearly in log error vs log minutes) is inverted at SIDM's error e_i; the
    multiplier is m_needed / m_i (``where`` "interpolated"). Nothing is capped: when e_i is
    below the baseline's best, the baseline does not reach it on the grid and the entry is
    ``where`` "beyond" with ``multiplier`` None and ``at_least`` = largest size / m_i; when e_i
    is above the baseline's error at the smallest size, ``where`` "below" with ``at_most`` =
    smallest size / m_i. Each entry: {minutes, where, multiplier, at_least, at_most}."""
    m = np.log(np.asarray(minutes, float))
    b = np.minimum.accumulate(np.log(np.asarray(without_sidm, float)))
    out = []
    for mi, e, mins in zip(m, np.log(np.asarray(with_sidm, float)), minutes, strict=True):
        row = {"minutes": float(mins), "where": "interpolated", "multiplier": None, "at_least": None, "at_most": None}
        if e < b[-1]:
            row.update(where="beyond", at_least=math.exp(m[-1] - mi))
        elif e > b[0]:
            row.update(where="below", at_most=math.exp(m[0] - mi))
        elif e == b[0]:
            row["multiplier"] = math.exp(m[0] - mi)
        else:
            j = int(np.argmax(b <= e))  # first size where the baseline reaches e
            t = (e - b[j - 1]) / (b[j] - b[j - 1]) if b[j] != b[j - 1] else 1.0
            row["multiplier"] = math.exp(m[j - 1] + t * (m[j] - m[j - 1]) - mi)
        out.append(row)
    return out


def multiplier_text(p: dict) -> str:
    """One entry of ``data_multipliers`` as text: "2.3x", "beyond the grid (> 4x)", "< 0.5x"."""
    if p["where"] == "beyond":
        return f"beyond the grid (> {p['at_least']:.2g}x)"
    if p["where"] == "below":
        return f"< {p['at_most']:.2g}x (below the grid)"
    return f"{p['multiplier']:.2g}x"


def open_loop_drift(model: Sidm | None, x0_seq: np.ndarray, s_seq: np.ndarray, features, horizon: int,
                    system: str = "novice") -> float:
    """Mean position error [m] after ``horizon`` open-loop steps.

    ``s_seq`` [T+1, n_state] are the measured states, ``x0_seq`` [T, n_extra] the per-step
    inputs that are not predicted (actions, the terrain patch under the measured path), and
    ``features(s, extra) -> x`` builds the model input. Rollouts start every ``horizon``
    steps; the position is channels 0 and 1 of the state. ``model`` None predicts no change."""
    errs = []
    for t0 in range(0, len(x0_seq) - horizon + 1, horizon):
        s = s_seq[t0].copy()
        for t in range(t0, t0 + horizon):
            if model is not None:
                s = s + model.predict(system, features(s[None], x0_seq[t][None]))[0]
        errs.append(float(np.linalg.norm(s[:2] - s_seq[t0 + horizon][:2])))
    return float(np.mean(errs)) if errs else math.nan
