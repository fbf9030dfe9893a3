"""Effect selection: folds, locked test set, held-out evidence, bootstrap, look-alikes, black box.

Procedure (see docs/calibration.md):

1. Whole episodes (or contiguous time blocks of long recordings) are split into a locked test
   set (never used for any decision) and a training pool, which is split into K folds; the
   blocks of a recording next to a held-out block are purged from its training set (a gap).
2. Each round, every remaining candidate is added to the accepted set; model + candidate are
   fit on the other folds and scored on the held-out fold (one-step and multi-step open-loop),
   so every training unit gets a held-out loss with and without the candidate.
3. Evidence (:func:`gain_evidence`): the held-out gain (a held-out likelihood ratio) and its
   moving-block bootstrap interval give a level, strong / moderate / weak / none, with its
   numbers. A candidate enters the model at moderate or better when also (c) the 95 %
   bootstrap interval of its primary parameter excludes the no-effect value and (d) it improves
   the out-of-bag loss in at least ``min_stability`` of the bootstrap replicates. Candidates
   with the same held-out fit are ranked by catalogue order and reported as look-alikes, never
   by float noise. When no single candidate enters, the best one is fitted jointly with each
   other (search over sets); a backward pass prunes effects the others made redundant.
4. A black-box regressor on the remaining one-step residual (random Fourier features, ridge)
   checks for structure the catalogue cannot explain (held-out R² with a paired test).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import stats as st

from hilstack.calibration import axis
from hilstack.calibration.effects import CATALOGUE, is_look_alike, separating_excitation
from hilstack.calibration.model_api import BatchLosses, FittedModel, Model, PhaseAlong, ResidualRows
from hilstack.calibration.models import FittedAxis


@dataclass(frozen=True)
class SelectionConfig:
    """Statistical settings (defaults are those used in docs/calibration.md)."""

    k_folds: int = 5
    test_fraction: float = 0.2
    alpha: float = 0.05
    min_gain: float = 0.02  # relative reduction of the held-out loss
    n_boot: int = 40
    min_stability: float = 0.8
    #: the stability check's replicates are extended (to 40, 80, 160, ... up to this many) while
    #: the 95 % Monte Carlo interval of the stability still contains ``min_stability``, so the
    #: verdict does not depend on how many replicates were asked for (see :func:`bootstrap_effect`)
    n_boot_max: int = 160
    horizon_s: float = 1.0
    min_episodes: int = 20
    max_rounds: int = 6
    bb_alpha: float = 0.01
    bb_min_r2: float = 0.05
    power: float = 0.8
    #: block-bootstrap replicates of the held-out gain (cheap: sums of held-out losses, no refits)
    n_boot_gain: int = 2000
    #: evidence levels: the held-out gain's block-bootstrap quantile that must be above 0
    #: (strong: the 0.5 % quantile, moderate: 2.5 %, weak: 20 %; see :func:`gain_evidence`)
    strong_quantile: float = 0.005
    moderate_quantile: float = 0.025
    weak_quantile: float = 0.2
    #: units of the same recording next to a held-out block that are left out of its training set
    purge_gap: int = 1
    #: search over sets (axis model): how many sets the beam keeps per size, and the largest set
    beam_width: int = 3
    max_set_size: int = 3


@dataclass
class Norms:
    """Normalizers (variances) of the four scored channels, fixed from the training pool.

    They only make the per-channel numbers readable: the selection score is a log-ratio per
    channel (see :func:`heldout_gain`), which no per-channel scale changes. ``horizon`` is the
    open-loop horizon [samples] the cheap out-of-bag loss also scores.
    """

    one_x: float
    one_v: float
    multi_x: float
    multi_v: float
    horizon: int = 0


#: The channels of the axis model's selection score, in the order of :func:`episode_loss`.
LOSS_CHANNELS = ("one_step_x", "one_step_v", "multi_step_x", "multi_step_v")


def compute_norms(preps: list[axis.Prepared]) -> Norms:
    dx = np.concatenate([np.diff(p.ep.x) for p in preps])
    dv = np.concatenate([np.diff(p.v_obs) for p in preps])
    x = np.concatenate([p.ep.x for p in preps])
    v = np.concatenate([p.v_obs for p in preps])
    tiny = 1e-300
    return Norms(float(np.var(dx)) + tiny, float(np.var(dv)) + tiny, float(np.var(x)) + tiny, float(np.var(v)) + tiny)


def episode_loss(s: axis.Scores, nm: Norms) -> np.ndarray:
    """Per-channel normalized MSE of one episode, in the order of :data:`LOSS_CHANNELS`."""
    one_n, multi_n = max(s.one_n, 1), max(s.multi_n, 1)
    return np.array([s.one_sse["x"] / one_n / nm.one_x, s.one_sse["v"] / one_n / nm.one_v,
                     s.multi_sse["x"] / multi_n / nm.multi_x, s.multi_sse["v"] / multi_n / nm.multi_v])


def _log_ratio(base: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """log(base / cand) per row and channel; a tiny floor per channel keeps exact zeros finite."""
    floor = 1e-12 * (np.mean(base, axis=0) + 1e-300)
    return np.log(base + floor) - np.log(cand + floor)


def heldout_gain(base: np.ndarray, cand: np.ndarray) -> float:
    """Relative held-out gain of ``cand`` losses over ``base`` losses (one row per episode).

    Scalar losses (one per episode): 1 − mean(cand)/mean(base). Per-channel losses (episodes ×
    channels, the axis model): every channel is scored against its own noise level. With a
    Gaussian likelihood whose noise variance is estimated per channel from the data (its
    maximum-likelihood value is the channel's MSE), the change of the log-likelihood per sample is
    the log of the channel's MSE ratio; the gain is 1 − exp(mean over channels of log(MSE_cand /
    MSE_base)), i.e. one minus the geometric mean of the per-channel MSE ratios. A channel sitting
    at its noise floor (e.g. a quantised velocity) has a ratio of 1 whatever its size, so it
    cannot drown a real effect in another channel, and one-step and multi-step (open-loop)
    channels weigh the same.
    """
    base, cand = np.asarray(base, float), np.asarray(cand, float)
    if base.ndim == 1:
        return float(1.0 - cand.mean() / base.mean())
    return float(1.0 - np.exp(-np.mean(_log_ratio(base.sum(0)[None], cand.sum(0)[None]))))


#: Evidence levels, strongest first. An effect enters the model at "moderate" or better.
LEVELS = ("strong", "moderate", "weak", "none")
ACCEPT_LEVELS = ("strong", "moderate")


@dataclass
class Evidence:
    """How strongly held-out data support a candidate (see :func:`gain_evidence`).

    Attributes:
        level: strong / moderate / weak / none.
        gain: held-out gain (point estimate over all held-out units).
        interval: 95 % block-bootstrap interval of the gain.
        lower_strong: the bootstrap quantile the "strong" level needs above 0 (0.5 %).
        p_positive: fraction of bootstrap replicates with a positive gain.
        n_units: held-out units (episodes or time blocks) the bootstrap resamples.
        block: bootstrap block length [units].
    """

    level: str
    gain: float
    interval: list[float]
    lower_strong: float
    p_positive: float
    n_units: int
    block: int

    def to_dict(self) -> dict:
        return {"level": self.level, "gain": self.gain, "interval": self.interval,
                "lower_strong": self.lower_strong, "p_positive": self.p_positive, "n_units": self.n_units,
                "block": self.block}

    def at_least(self, level: str) -> bool:
        return LEVELS.index(self.level) <= LEVELS.index(level)


def _gain_rows(base: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """Held-out gain of summed losses; ``base``/``cand`` are (replicates, units[, channels])."""
    b, c = base.sum(1), cand.sum(1)
    if b.ndim == 1:
        return 1.0 - c / np.maximum(b, 1e-300)
    floor = 1e-12 * (b.mean(0) + 1e-300)
    return 1.0 - np.exp(-np.mean(np.log(b + floor) - np.log(c + floor), axis=1))


def block_indices(n: int, block: int, n_boot: int, rng: np.random.Generator) -> np.ndarray:
    """Moving-block bootstrap: (n_boot, n) unit indices, runs of ``block`` consecutive units."""
    block = max(1, min(block, n))
    n_blocks = int(math.ceil(n / block))
    starts = rng.integers(0, n - block + 1, (n_boot, n_blocks))
    return (starts[:, :, None] + np.arange(block)[None, None, :]).reshape(n_boot, -1)[:, :n]


def gain_evidence(base: np.ndarray, cand: np.ndarray, cfg: SelectionConfig, seed: int = 0,
                  block: int = 1, min_gain: float | None = None) -> Evidence:
    """Evidence level of ``cand`` held-out losses over ``base`` (one row per held-out unit, pool order).

    The effect size is the held-out gain (a held-out likelihood ratio: it charges every parameter
    by its out-of-sample cost, like an information criterion, cf. Stone 1977); its uncertainty is a
    moving-block bootstrap over held-out units (``block`` > 1 when units are neighbouring time
    blocks of one recording, which are correlated). Levels, each also needing gain ≥ ``min_gain``
    (the effect size):

    * strong: the 0.5 % bootstrap quantile of the gain is above 0,
    * moderate: the 2.5 % quantile is above 0 (the 95 % interval excludes no gain),
    * weak: the 20 % quantile is above 0 (4 in 5 replicates say it helps),
    * none: otherwise.

    No correction towards zero for the number of candidates or rounds: with 2–12 recordings such a
    corrected test cannot reach significance at all. False alarms are instead measured on clean
    data (docs/calibration.md: at most 5 % at "strong").
    """
    base, cand = np.asarray(base, float), np.asarray(cand, float)
    min_gain = cfg.min_gain if min_gain is None else min_gain
    n = base.shape[0]
    gain = heldout_gain(base, cand)
    if n == 0 or not np.isfinite(gain):
        return Evidence("none", float(gain) if np.isfinite(gain) else 0.0, [0.0, 0.0], 0.0, 0.0, n, block)
    rng = np.random.default_rng(seed + 104729)
    idx = block_indices(n, block, cfg.n_boot_gain, rng)
    g = _gain_rows(base[idx], cand[idx])
    q = np.quantile(g, [cfg.strong_quantile, cfg.moderate_quantile, cfg.weak_quantile, 0.975])
    if gain >= min_gain and q[0] > 0:
        level = "strong"
    elif gain >= min_gain and q[1] > 0:
        level = "moderate"
    elif gain >= min_gain and q[2] > 0:
        level = "weak"
    else:
        level = "none"
    return Evidence(level, float(gain), [float(q[1]), float(q[3])], float(q[0]), float(np.mean(g > 0)), n, block)


#: Two candidates whose held-out losses agree to this relative tolerance on every unit are the same
#: fit (e.g. a force offset and a slope on a fixed axis: the same column); ranking them by their
#: gains would be ranking by floating-point noise, which differs between CPUs.
TIE_RTOL = 1e-6


def same_fit(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.allclose(a, b, rtol=TIE_RTOL, atol=1e-300))


def rank_candidates(results: list, order: list[str]) -> list:
    """Sort by held-out gain, best first; candidates with the same held-out losses (:func:`same_fit`)
    form a tie group ordered by ``order`` (the catalogue order), never by float noise."""
    by_gain = sorted(results, key=lambda r: (-r.gain, order.index(r.name) if r.name in order else len(order)))
    groups: list[list] = []
    for r in by_gain:
        g = next((g for g in groups if same_fit(g[0].losses, r.losses)), None)
        if g is None:
            groups.append([r])
        else:
            g.append(r)
    out = []
    for g in groups:
        g.sort(key=lambda r: order.index(r.name) if r.name in order else len(order))
        for r in g[1:]:
            r.tied_with = g[0].name
        out.extend(g)
    return out


class Folds(list):
    """Fold index arrays over the training pool, plus the units purged from each fold's training set.

    ``purge[i]``: units of the same recording next to fold i's held-out block (``purge_gap`` on
    each side), left out when fold i is held out, so that neighbouring samples (shared context,
    correlated noise) do not leak from training into the held-out block.
    """

    def __init__(self, folds, purge: dict[int, set[int]] | None = None, block: int = 1):
        super().__init__(folds)
        self.purge = purge or {}
        self.block = block

    def train(self, i: int) -> list[int]:
        gone = self.purge.get(i, set())
        return [j for f, fold in enumerate(self) if f != i for j in fold if j not in gone]


def _unit_order(preps) -> list[tuple[str, int] | None]:
    """(recording, start sample) of each segment cut from a recording; None for a whole episode."""
    out = []
    for p in preps:
        meta = p.ep.meta
        out.append((str(meta["segment_of"]), int(meta.get("segment_start", 0))) if "segment_of" in meta else None)
    return out


def purge_neighbours(preps, folds: list[np.ndarray], gap: int) -> dict[int, set[int]]:
    """For each fold, the units within ``gap`` positions (same recording, time order) of its units."""
    order = _unit_order(preps)
    rec: dict[str, list[tuple[int, int]]] = {}
    for j, o in enumerate(order):
        if o is not None:
            rec.setdefault(o[0], []).append((o[1], j))
    pos: dict[int, tuple[str, int]] = {}
    seq: dict[str, list[int]] = {}
    for name, lst in rec.items():
        seq[name] = [j for _, j in sorted(lst)]
        for k, j in enumerate(seq[name]):
            pos[j] = (name, k)
    out: dict[int, set[int]] = {}
    pool = {int(j) for fold in folds for j in fold}
    for i, fold in enumerate(folds):
        held = {int(j) for j in fold}
        near: set[int] = set()
        for j in held:
            if j in pos and gap > 0:
                name, k = pos[j]
                s_ = seq[name]
                near.update(s_[max(0, k - gap): k + gap + 1])
        out[i] = (near - held) & pool
    return out


def cv_split(n: int, cfg: SelectionConfig, seed: int,
                   locked: np.ndarray | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """(locked test indices, list of K fold index arrays over the training pool).

    ``locked`` (bool per unit): segments of long recordings, where the locked test set is the
    final block of each recording and the folds are contiguous blocks in time order (blocked
    time-series cross-validation: a held-out block is never interleaved with training data).
    Otherwise whole episodes are shuffled (seeded) into a test set and K folds.
    """
    if locked is not None and locked.any():
        test = np.flatnonzero(locked)
        pool = np.flatnonzero(~locked)
        k = max(2, min(cfg.k_folds, pool.size))
        return test, [np.asarray(b, dtype=int) for b in np.array_split(pool, k)]
    rng = np.random.default_rng(seed)
    order = rng.permutation(n)
    n_test = max(1, int(round(cfg.test_fraction * n))) if n >= 4 else 0
    test = np.sort(order[:n_test])
    pool = order[n_test:]
    k = max(2, min(cfg.k_folds, pool.size))
    folds = [np.sort(pool[i::k]) for i in range(k)]
    return test, folds


def paired_p(base: np.ndarray, cand: np.ndarray) -> float:
    """One-sided Wilcoxon signed-rank p-value that ``cand`` losses are lower than ``base``.

    Per-channel losses (episodes × channels) are compared per episode by the log-likelihood
    gain with each channel's noise variance estimated on all episodes (the channel's mean base
    MSE): d_e = mean over channels of (base_ec − cand_ec) / mean_e(base_ec). An episode where a
    channel's error is tiny (little motion) then contributes a tiny difference, not the unstable
    log of a ratio of two tiny numbers.
    """
    base, cand = np.asarray(base, float), np.asarray(cand, float)
    if base.ndim == 1:
        d = base - cand
        tol = 1e-12 * (np.abs(base) + 1e-300)
    else:
        d = np.mean((base - cand) / (base.mean(axis=0) + 1e-300), axis=1)
        tol = np.full(d.shape, 1e-12)
    if np.all(np.abs(d) <= tol):
        return 1.0
    if d.size <= EXACT_SIGNED_RANK_MAX_N and (np.any(d == 0) or np.unique(np.abs(d)).size < d.size):
        return signed_rank_exact_p(d)
    try:
        return float(st.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue)
    except ValueError:
        return 1.0


#: Up to this many units, a signed-rank test with zeros or ties is exact by enumeration (scipy's
#: wilcoxon switches to a generic permutation test there, ~1 s per call at 13 units).
EXACT_SIGNED_RANK_MAX_N = 13


def signed_rank_exact_p(d: np.ndarray) -> float:
    """Exact one-sided p of the Wilcoxon signed-rank statistic (zeros split, ties averaged).

    T = sum of the ranks of |d| over positive d + half the ranks of the zeros. Under the null
    every sign is equally likely, so all 2^m sign patterns of the m non-zero differences are
    enumerated at once (a bit matrix times the ranks); p = P(T ≥ T_observed). The same value as
    ``scipy.stats.wilcoxon(d, alternative="greater", zero_method="zsplit")``, without its
    generic permutation machinery.
    """
    d = np.asarray(d, float)
    r = st.rankdata(np.abs(d))
    t_obs = float(r[d > 0].sum() + 0.5 * r[d == 0].sum())
    rn = r[d != 0]
    bits = (np.arange(2**rn.size)[:, None] >> np.arange(rn.size)[None, :]) & 1
    t = bits @ rn + 0.5 * float(r[d == 0].sum())
    return float(np.mean(t >= t_obs - 1e-9 * max(abs(t_obs), 1.0)))


@dataclass
class CandidateResult:
    name: str
    losses: np.ndarray  # held-out loss per training-pool episode (pool order)
    gain: float
    p_value: float
    fitted: FittedModel | None = None
    interval: list[float] | None = None
    stability: float | None = None
    boot_values: list[float] = field(default_factory=list)
    verdict: str = ""
    evidence: Evidence | None = None
    tied_with: str | None = None


def crossval_losses(model: Model, preps, folds, effects, nm, horizon: int,
                    start: FittedModel | None, search: list[str] | None) -> np.ndarray:
    """Held-out loss of every training-pool episode (pool order = concatenated folds)."""
    jobs = []
    for i, held in enumerate(folds):
        idx = folds.train(i) if isinstance(folds, Folds) else [j for f, fold in enumerate(folds) if f != i
                                                               for j in fold]
        train = [preps[j] for j in idx]
        fitted = model.fit(train, effects, refine=False, start=start, search=search)
        jobs.extend((preps[j], fitted) for j in held)
    return np.asarray(_episode_losses(model, jobs, horizon, nm))


def _episode_losses(model: Model, jobs, horizon: int, nm) -> list:
    """Held-out losses of (episode, fitted) pairs: in one batch when the model can (axis), else one by one."""
    if isinstance(model, BatchLosses):
        return model.episode_losses(jobs, horizon, nm)
    return [model.episode_loss(p, f, horizon, nm) for p, f in jobs]


def _oob_losses(model: Model, jobs, nm) -> list:
    if isinstance(model, BatchLosses):
        return model.oob_losses(jobs, nm)
    return [model.oob_loss(p, f, nm) for p, f in jobs]


def _wrong_sign(interval: list[float], spec) -> bool:
    """The whole interval lies on the side of the no-effect value that has no physical meaning."""
    sign = spec.physical_sign
    return bool(sign) and (interval[1] < spec.no_effect if sign > 0 else interval[0] > spec.no_effect)


def _excludes(interval: list[float], no_effect: float) -> bool:
    lo, hi = interval
    if math.isinf(no_effect):
        return math.isfinite(hi)
    return lo > no_effect or hi < no_effect


def wilson_interval(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a proportion k/n (the Monte Carlo error of a bootstrap share)."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    d = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / d
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return mid - half, mid + half


#: replicate counts the stability check may extend to (each a prefix of the next: same seed)
BOOT_SCHEDULE = (40, 80, 160, 320, 640)


def bootstrap_effect(model: Model, preps, pool_idx: np.ndarray, base: FittedModel, effects: list[str],
                     name: str, n_boot: int, seed: int, nm, n_boot_max: int | None = None,
                     min_stability: float = 0.8) -> tuple[list[float], float, list[float]]:
    """Episode bootstrap of the candidate's primary parameter and its out-of-bag stability.

    Returns (95 % interval, fraction of replicates whose out-of-bag loss improves, values).

    Sequential Monte Carlo (Gandy 2009): after ``n_boot`` replicates, while the 95 % Wilson
    interval of the stability still contains ``min_stability`` (the verdict is within Monte Carlo
    error of its threshold), the replicates are extended to the next count of
    :data:`BOOT_SCHEDULE` up to ``n_boot_max``. Replicates are drawn from one seeded stream, so
    20 replicates are the first 20 of 40: runs asked for 20, 25 or 40 replicates that are still
    undecided continue on the same replicates and reach the same verdict.
    """
    rng = np.random.default_rng(seed + 7919)
    pool = [preps[i] for i in pool_idx]
    vals, wins, tried = [], 0, 0
    # A position-periodic load is measured along the phase of its fit on the whole pool, so a
    # replicate cannot flip its sign by moving to the other representation of the same load.
    ref = (model.fit(pool, effects + [name], refine=False, start=base, search=[name])
           if isinstance(base, PhaseAlong) and name in axis.PHASE_OF else None)
    targets = [n_boot] + [n for n in BOOT_SCHEDULE if n_boot < n <= (n_boot_max or n_boot)]
    for target in targets:
        reps = []  # (out-of-bag episodes, fit without, fit with) per replicate, scored in one batch below
        while len(vals) < target:
            counts = np.bincount(rng.integers(0, len(pool), len(pool)), minlength=len(pool)).astype(float)
            b = model.fit(pool, effects, weights=counts, refine=False, start=base, search=[])
            c = model.fit(pool, effects + [name], weights=counts, refine=False, start=base, search=[name])
            vals.append(c.primary(name) if ref is None else c.primary_along(name, ref))
            oob = np.flatnonzero(counts == 0)
            if oob.size:
                reps.append((oob, b, c))
        jobs = [(pool[i], fit) for oob, b, c in reps for fit in (b, c) for i in oob]
        losses = iter(_oob_losses(model, jobs, nm))
        for oob, _b, _c in reps:
            tried += 1
            lb = np.sum([np.atleast_1d(next(losses)) for _ in oob], axis=0)
            lc = np.sum([np.atleast_1d(next(losses)) for _ in oob], axis=0)
            wins += heldout_gain(lb[None], lc[None]) > 0
        lo, hi = wilson_interval(wins, tried)
        if not lo <= min_stability <= hi:
            break  # the stability is clear of its threshold beyond Monte Carlo error
    arr = np.asarray(vals, float)
    interval = [float(np.nanpercentile(arr, 2.5)), float(np.nanpercentile(arr, 97.5))]
    return interval, (wins / tried if tried else 0.0), [float(v) for v in arr]


@dataclass
class SelectionResult:
    accepted: list[CandidateResult]
    ambiguous: list[dict]
    rounds: list[dict]
    final: FittedModel
    nominal: FittedModel
    skipped: dict[str, str]
    test_idx: np.ndarray
    folds: Folds
    norms: Norms
    horizon: int
    #: candidates with weak or better evidence that did not enter the model (last round)
    findings: list[dict] = field(default_factory=list)


def select_effects(model: Model, preps: list[axis.Prepared], cfg: SelectionConfig, seed: int = 0,
                   log: Callable[[str], None] = lambda s: None) -> SelectionResult:
    """Stepwise selection of effects by held-out evidence (see module docstring)."""
    locked = np.array([bool(p.ep.meta.get("locked_test")) for p in preps])
    test_idx, raw_folds = cv_split(len(preps), cfg, seed, locked)
    pool_idx = np.concatenate(raw_folds)
    segmented = any(o is not None for o in _unit_order(preps))
    # Neighbouring time blocks of one recording are correlated: resample runs of them.
    block = max(1, int(round(pool_idx.size ** (1 / 3)))) if segmented else 1
    folds = Folds(raw_folds, purge_neighbours(preps, raw_folds, cfg.purge_gap), block)
    pool = [preps[i] for i in pool_idx]
    nm = model.norms(pool)
    horizon = max(2, int(round(cfg.horizon_s / preps[0].period_s)))
    if isinstance(nm, Norms):
        nm.horizon = horizon
    candidates, skipped = model.candidate_effects(preps)
    n_purged = sum(len(v) for v in folds.purge.values())
    log(f"{len(preps)} episodes: {test_idx.size} locked for test, {pool_idx.size} in {len(folds)} folds"
        + (f" ({n_purged} neighbouring unit(s) purged from the training sets, bootstrap blocks of {block})"
           if segmented else "") + f"; {len(candidates)} candidate effects")
    order = list(model.catalogue)

    def ev(base, cand, salt: int = 0) -> Evidence:
        return gain_evidence(base, cand, cfg, seed + salt, folds.block)

    nominal = model.fit(pool, [])
    current = nominal
    accepted: list[CandidateResult] = []
    ambiguous: list[dict] = []
    rounds: list[dict] = []
    findings: list[dict] = []
    used = 0  # rounds used (a pair accepted together uses two)
    for rnd in range(cfg.max_rounds):
        if used >= cfg.max_rounds:
            break
        used += 1
        effects = list(current.effects)
        candidates, skipped = model.candidate_effects(preps, tuple(effects))
        remaining = [c for c in candidates if c not in effects]
        if not remaining:
            break
        base_loss = crossval_losses(model, preps, folds, effects, nm, horizon, current, [])
        results = []
        for name in remaining:
            losses = crossval_losses(model, preps, folds, effects + [name], nm, horizon, current, [name])
            r = CandidateResult(name, losses, heldout_gain(base_loss, losses), paired_p(base_loss, losses))
            r.evidence = ev(base_loss, losses, rnd)
            results.append(r)
            iv = r.evidence.interval
            log(f"  round {rnd + 1}: {name:18s} held-out gain {r.gain:+.3f} [{iv[0]:+.3f}, {iv[1]:+.3f}]  "
                f"{r.evidence.level}")
        results = rank_candidates(results, order)
        passing = [r for r in results if r.evidence.at_least("moderate")]
        round_doc = {
            "round": rnd + 1,
            "base_effects": effects,
            "base_heldout_loss": base_loss.mean(axis=0).tolist() if base_loss.ndim > 1 else float(base_loss.mean()),
            "candidates": [{"name": r.name, "heldout_gain": r.gain, "p_value": r.p_value,
                            "evidence": r.evidence.to_dict(), "tied_with": r.tied_with} for r in results],
        }
        if base_loss.ndim > 1:
            round_doc["loss_channels"] = list(LOSS_CHANNELS)
            for c, r in zip(round_doc["candidates"], results, strict=True):
                c["channel_gain"] = (1.0 - r.losses.sum(0) / base_loss.sum(0)).tolist()
        # Look-alikes: test each of the best candidates in the presence of the others, so that one
        # that only mimics the true effect (a deadband for Coulomb friction) cannot block it.
        pairs = (pair_tests(model, preps, folds, effects, nm, horizon, current, results, cfg, ev)
                 if model.pair_tests else [])
        if pairs:
            round_doc["pairs"] = pairs
            dominated = {d["explained"] for d in pairs if d["explained"]
                         and any(r.name == d["explains"] for r in passing)}
            passing = [r for r in passing if r.name not in dominated] + [r for r in passing if r.name in dominated]
            for r in passing:
                if r.name in dominated:
                    r.verdict = "rejected: explained by " + next(
                        d["explains"] for d in pairs if d["explained"] == r.name)
        winner = None
        for r in passing:
            if r.verdict:
                continue
            if r.tied_with is not None:
                r.verdict = f"same held-out fit as {r.tied_with} (reported as a look-alike)"
                continue
            stuck = {}
            if model.reports_bounds:
                bound = model.fit(pool, effects + [r.name], refine=False, start=current, search=[r.name])
                stuck = {h: v for h, v in bound.at_bound.items() if h == axis.HYPER_OF.get(r.name)}
            if stuck:
                r.verdict = (f"rejected: estimate at the edge of its search range even after widening it "
                             f"({', '.join(f'{h}={v:.4g}' for h, v in stuck.items())}); the data do not bound it")
                log(f"  round {rnd + 1}: {r.name}: {r.verdict}")
                continue
            r.interval, r.stability, r.boot_values = bootstrap_effect(
                model, preps, pool_idx, current, effects, r.name, cfg.n_boot, seed + rnd, nm, cfg.n_boot_max,
                cfg.min_stability)
            ok_int = _excludes(r.interval, model.catalogue[r.name].no_effect)
            ok_stab = r.stability >= cfg.min_stability
            bad_sign = _wrong_sign(r.interval, model.catalogue[r.name])
            r.verdict = "accepted" if ok_int and ok_stab and not bad_sign else (
                "rejected: bootstrap interval includes the no-effect value" if not ok_int
                else "rejected: the estimate has the sign without physical meaning" if bad_sign
                else f"rejected: unstable under episode bootstrap ({r.stability:.2f})")
            log(f"  round {rnd + 1}: {r.name}: interval {r.interval}, stability {r.stability:.2f} -> {r.verdict}")
            if r.verdict == "accepted":
                winner = r
                break
        for r in passing:
            if r.verdict.startswith("rejected: explained by"):
                log(f"  round {rnd + 1}: {r.name}: {r.verdict}")
        round_doc["decisions"] = [
            {"name": r.name, "verdict": r.verdict, "interval": r.interval, "stability": r.stability}
            for r in passing if r.verdict
        ]
        rounds.append(round_doc)
        # Search over sets: when no single candidate enters, the best one together with each other
        # candidate (friction + lag, delay + Coulomb, gravity + friction must often enter together).
        # The lead is the best candidate whose parameter the data bound (one at the edge of its search range
        # stays unbounded with a partner, and pairing it costs a refit per candidate).
        lead = next((r for r in results if "edge of its search range" not in r.verdict), None)
        if (winner is None and model.pair_tests and len(results) > 1 and used < cfg.max_rounds
                and lead is not None and lead.gain >= cfg.min_gain and lead.evidence.at_least("weak")):
            found = beam_sets(model, preps, folds, pool_idx, effects, nm, horizon, current, results, base_loss,
                              cfg, seed + rnd, round_doc, log, ev, min(cfg.max_set_size, cfg.max_rounds - used + 1))
            if found:
                used += len(found) - 1  # a set of k effects uses k rounds
                current = model.fit(pool, effects + [r.name for r in found], refine=True, start=current)
                for r in found:
                    r.fitted = current
                    accepted.append(r)
                log(f"accepted the set {' + '.join(r.name for r in found)}")
                continue
        if winner is None:
            # Nothing enters the model: what the data hint at is still reported, with its numbers.
            findings = [{"name": r.name, "round": rnd + 1, "level": r.evidence.level, "heldout_gain": r.gain,
                         "interval": r.evidence.interval, "p_positive": r.evidence.p_positive,
                         "why_not_accepted": r.verdict or ("evidence below moderate" if not
                                                           r.evidence.at_least("moderate") else "")}
                        for r in results if r.evidence.at_least("weak")]
            break
        # Look-alikes that explain the held-out data about as well as the winner, and candidates
        # with the very same held-out fit (never ranked against each other by float noise).
        table = model.look_alikes
        for r in results:
            if r is winner:
                continue
            tied = r.tied_with == winner.name
            if not tied and (r not in passing or not is_look_alike(winner.name, r.name, table)):
                continue
            sep = ev(r.losses, winner.losses, 17)
            if tied or not sep.at_least("moderate"):
                excitation = (separating_excitation(winner.name, r.name, table) if is_look_alike(
                    winner.name, r.name, table) else "an excitation in which the two act differently")
                ambiguous.append({
                    "effects": [winner.name, r.name],
                    "chosen": winner.name,
                    "heldout_gain": {winner.name: winner.gain, r.name: r.gain},
                    "p_value_separation": paired_p(r.losses, winner.losses),
                    "evidence_separation": sep.to_dict(),
                    "identical_fit": tied,
                    "excitation": excitation,
                })
                log(f"  ambiguous: {winner.name} vs {r.name} ({'identical held-out fit' if tied else sep.level}); "
                    f"separate with {excitation}")
        prev = current
        current = model.fit(pool, effects + [winner.name], refine=True, start=current)
        if model.shift_interval_to_refined:
            # The bootstrap re-fits on the cached grid (no new replays); the refined pool fit
            # replays off-grid. Centre the percentile interval on the refined estimate: shift it
            # by (refined − grid estimate on the same pool), the grid's interpolation bias.
            plain = model.fit(pool, effects + [winner.name], refine=False, start=prev, search=[winner.name])
            delta = current.primary(winner.name) - plain.primary(winner.name)
            winner.interval = [winner.interval[0] + delta, winner.interval[1] + delta]
        winner.fitted = current
        accepted.append(winner)
        log(f"accepted {winner.name} ({winner.evidence.level}): {current.effect_params(winner.name)}")
    if len(accepted) > 1:
        current, accepted, ambiguous = prune_effects(model, preps, folds, pool, current, accepted, ambiguous, nm,
                                                     horizon, cfg, rounds, log, ev)
    if accepted and model.pair_tests:
        ambiguous += swap_look_alikes(model, preps, folds, current, accepted, ambiguous, nm, horizon, cfg, log, ev)
    if not accepted:
        log("no effect reached moderate evidence" + (
            f"; weak or better: {', '.join(f['name'] + ' (' + f['level'] + ')' for f in findings)}" if findings else ""))
    return SelectionResult(accepted, ambiguous, rounds, current, nominal, skipped, test_idx, folds, nm, horizon,
                           findings)


def _by_order(names, order: list[str]) -> list[str]:
    return sorted(names, key=lambda n: (order.index(n) if n in order else len(order), n))


def beam_sets(model, preps, folds, pool_idx, effects, nm, horizon, current, results: list[CandidateResult],
              base_loss, cfg: SelectionConfig, seed: int, round_doc: dict, log, ev, max_size: int):
    """When no single candidate enters: a beam search over sets of candidates.

    Effects may only help together (on EMPS, Coulomb friction alone makes some open-loop windows
    worse; with the force offset it explains the data; a delay and Coulomb friction, a lag and
    friction). The beam starts from the ``cfg.beam_width`` best single candidates (by held-out gain,
    whether or not they passed) and grows each set by every other candidate, up to ``max_size``
    effects; every child set is fitted jointly (the hyper-parameters of all its members searched
    together, the linear coefficients of the whole model by least squares) and scored by the same
    cross-validated held-out losses. The ``beam_width`` best children of one size seed the next.
    A set enters when, at the smallest size where any does, (a) it has moderate evidence against
    the model without it, (b) every member has moderate evidence against the set without that
    member (each is needed in the presence of the others), and (c) every member passes the
    bootstrap checks with the others in the model. With ``beam_width`` 1 this is the former
    "pair move" (the best single candidate with each other one). Returns the accepted
    CandidateResults, or None.
    """
    order = list(model.catalogue)
    names = [r.name for r in results if "edge of its search range" not in r.verdict and r.tied_with is None]
    losses: dict[frozenset, np.ndarray] = {frozenset([r.name]): r.losses for r in results}
    losses[frozenset()] = base_loss

    def loss_of(key: frozenset) -> np.ndarray:
        if key not in losses:
            members = _by_order(key, order)
            losses[key] = crossval_losses(model, preps, folds, effects + members, nm, horizon, current, members)
        return losses[key]

    beam = [frozenset([n]) for n in names][: max(1, cfg.beam_width)]
    tried: list[dict] = []
    doc = {"beam_width": cfg.beam_width, "tried": tried, "beams": [[_by_order(s, order) for s in beam]]}
    round_doc["set_search"] = doc
    for _size in range(2, max_size + 1):
        children: dict[frozenset, float] = {}
        for s in beam:
            for n in names:
                key = s | {n}
                if n in s or key in children:
                    continue
                children[key] = heldout_gain(base_loss, loss_of(key))
        if not children:
            break
        ranked = sorted(children, key=lambda k: (-children[k], _by_order(k, order)))
        passing = []
        for key in ranked:
            e_set = ev(base_loss, losses[key], 31)
            adding = {m: ev(loss_of(key - {m}), losses[key], 37 + i) for i, m in enumerate(_by_order(key, order))}
            tried.append({"effects": _by_order(key, order), "heldout_gain": e_set.gain, "evidence": e_set.to_dict(),
                          "adding": {m: e.to_dict() for m, e in adding.items()}})
            if e_set.at_least("moderate") and all(e.at_least("moderate") for e in adding.values()):
                passing.append((key, e_set))
        for key, e_set in passing:
            members = _by_order(key, order)
            out = []
            for m in members:
                others = [o for o in members if o != m]
                res = CandidateResult(m, losses[key], e_set.gain, paired_p(base_loss, losses[key]), evidence=e_set)
                res.interval, res.stability, res.boot_values = bootstrap_effect(
                    model, preps, pool_idx, current, effects + others, m, cfg.n_boot, seed, nm, cfg.n_boot_max,
                    cfg.min_stability)
                ok = (_excludes(res.interval, model.catalogue[m].no_effect) and res.stability >= cfg.min_stability
                      and not _wrong_sign(res.interval, model.catalogue[m]))
                res.verdict = (f"accepted (in the set {' + '.join(members)})" if ok
                               else "rejected: set member fails the bootstrap")
                log(f"  set {' + '.join(members)}: {m} interval {res.interval}, stability {res.stability:.2f}")
                out.append(res)
            doc["decision"] = [{"name": r.name, "verdict": r.verdict, "interval": r.interval,
                                "stability": r.stability} for r in out]
            if all(r.verdict.startswith("accepted") for r in out):
                return out
        beam = ranked[: max(1, cfg.beam_width)]
        doc["beams"].append([_by_order(s, order) for s in beam])
    return None


def swap_look_alikes(model, preps, folds, current, accepted, ambiguous, nm, horizon, cfg, log, ev) -> list[dict]:
    """Swap each accepted effect for each of its look-alikes that was never compared on equal terms.

    The order of acceptance can hide a look-alike: once Coulomb friction and an offset are in,
    direction-dependent friction (the same thing on every moving row) adds nothing and is never
    a rival. Each accepted effect is replaced by each look-alike that the model with the others
    offers; when neither model has moderate evidence over the other on held-out data, the pair is
    reported as ambiguous with the excitation that would separate it.
    """
    table = model.look_alikes
    names = [r.name for r in accepted]
    known = {frozenset(a["effects"]) for a in ambiguous}
    full = crossval_losses(model, preps, folds, list(current.effects), nm, horizon, current, [])
    out = []
    for name in names:
        rest = [e for e in current.effects if e != name]
        offered, _ = model.candidate_effects(preps, tuple(rest))
        for alt in offered:
            if alt in current.effects or not is_look_alike(name, alt, table) or frozenset({name, alt}) in known:
                continue
            swapped = crossval_losses(model, preps, folds, rest + [alt], nm, horizon, current, [alt])
            e_worse, e_better = ev(swapped, full, 43), ev(full, swapped, 47)
            if not (e_worse.at_least("moderate") or e_better.at_least("moderate")):
                excitation = separating_excitation(name, alt, table)
                out.append({"effects": [name, alt], "chosen": name,
                            "heldout_gain": {name: 0.0, alt: heldout_gain(full, swapped)},
                            "p_value_separation": min(paired_p(swapped, full), paired_p(full, swapped)),
                            "evidence_separation": e_worse.to_dict(), "identical_fit": same_fit(full, swapped),
                            "excitation": excitation, "found_by": "swap"})
                known.add(frozenset({name, alt}))
                log(f"  ambiguous (swap): {name} vs {alt}; separate with {excitation}")
    return out


def prune_effects(model, preps, folds, pool, current, accepted, ambiguous, nm, horizon, cfg, rounds, log, ev):
    """Backward pass: drop an accepted effect that the others made redundant.

    Stepwise selection can accept a look-alike first (an offset before the slope and the payload
    that explain it). Each accepted effect is removed in turn, the rest refit; if keeping it has
    less than moderate held-out evidence over the model without it, it goes.
    """
    full = crossval_losses(model, preps, folds, list(current.effects), nm, horizon, current, [])
    dropped = []
    for r in list(accepted):
        rest = [e for e in current.effects if e != r.name]
        without = crossval_losses(model, preps, folds, rest, nm, horizon, current, [])
        e_keep = ev(without, full, 53)
        if not e_keep.at_least("moderate"):
            log(f"pruned {r.name}: the other accepted effects explain it (gain of keeping it {e_keep.gain:+.3f}, "
                f"{e_keep.level})")
            dropped.append({"name": r.name, "gain_of_keeping": e_keep.gain, "evidence": e_keep.to_dict(),
                            "p_value": paired_p(without, full)})
            accepted = [a for a in accepted if a is not r]
            current = model.fit(pool, rest, refine=True, start=current)
            full = without
    if dropped:
        rounds.append({"round": "prune", "dropped": dropped})
        gone = {d["name"] for d in dropped}
        ambiguous = [a for a in ambiguous if a["chosen"] not in gone]
        for r in accepted:
            r.fitted = current
    return current, accepted, ambiguous


#: How many of a round's best candidates are tested in each other's presence.
PAIR_TOP = 3


def pair_tests(model, preps, folds, effects, nm, horizon, current, results: list[CandidateResult],
               cfg: SelectionConfig, ev) -> list[dict]:
    """Test the best candidates of a round in the presence of each other.

    For the top :data:`PAIR_TOP` candidates that help on their own (gain ≥ ``min_gain``, evidence
    weak or better), fit every pair (a, b) together. "a explains b" when adding a to b still has
    moderate evidence while adding b to a does not: b then only mimics part of a. Candidates with
    the same held-out fit as another are left out (they are reported as look-alikes).
    """
    top = [r for r in results if r.gain >= cfg.min_gain and r.evidence.at_least("weak")
           and r.tied_with is None][:PAIR_TOP]
    out = []
    for i in range(len(top)):
        for j in range(i + 1, len(top)):
            a, b = top[i], top[j]
            both = crossval_losses(model, preps, folds, effects + [a.name, b.name], nm, horizon, current,
                                   [a.name, b.name])
            a_adds, b_adds = ev(b.losses, both, 59), ev(a.losses, both, 61)
            # gain_adding[a]: held-out gain of adding a to a model that already has b (and vice versa)
            rec = {"effects": [a.name, b.name], "gain_adding": {a.name: a_adds.gain, b.name: b_adds.gain},
                   "evidence_adding": {a.name: a_adds.level, b.name: b_adds.level},
                   "explains": None, "explained": None}
            if a_adds.at_least("moderate") and not b_adds.at_least("moderate"):
                rec["explains"], rec["explained"] = a.name, b.name
            elif b_adds.at_least("moderate") and not a_adds.at_least("moderate"):
                rec["explains"], rec["explained"] = b.name, a.name
            out.append(rec)
    return out


# ----------------------------------------------------------------------------- black box


def _bb_features(p: axis.Prepared, k: np.ndarray, v: np.ndarray) -> np.ndarray:
    u = p.ep.u
    cols = [p.ep.x[k], v[k]]
    for lag in (0, 1, 2, 4, 8):
        cols.append(u[np.maximum(k - lag, 0)])
    if p.ep.vbat_v is not None:
        cols.append(p.ep.vbat_v[k])
    if p.ep.payload is not None:
        cols.append(p.ep.payload[k])
    return np.stack(cols, axis=1)


def _bb_basis(z: np.ndarray, edges: list[np.ndarray], rng_seed: int, bins_only: tuple[int, ...] = ()) -> np.ndarray:
    """Flexible basis on standardized inputs: per-input quantile-bin indicators (an additive
    piecewise-constant model, like boosted stumps: catches e.g. position-periodic forces), plus
    joint random Fourier features (smooth interactions) and the inputs themselves.

    Inputs in ``bins_only`` (the axis position) enter through their bins alone: a bin holds its
    value beyond the training range, whereas a linear or Fourier term in raw position
    extrapolates wildly on unbounded motion (a spinning motor, a driving vehicle) whose held-out
    fold lies at positions the training folds never reached.
    """
    rng = np.random.default_rng(rng_seed)
    n, d = z.shape
    smooth = [j for j in range(d) if j not in bins_only]
    zs = z[:, smooth]
    parts = [zs]
    for j in range(d):
        idx = np.clip(np.searchsorted(edges[j], z[:, j]), 0, len(edges[j]))
        onehot = np.zeros((n, len(edges[j]) + 1))
        onehot[np.arange(n), idx] = 1.0
        parts.append(onehot)
    W = rng.standard_normal((len(smooth), 80)) / np.exp(rng.uniform(np.log(0.3), np.log(3.0), 80))[None, :]
    parts.append(np.cos(zs @ W + rng.uniform(0, 2 * np.pi, 80)[None, :]))
    return np.concatenate(parts, axis=1)


def _ridge_gcv(F: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Ridge with the penalty chosen by generalized cross-validation (on training rows only)."""
    mu, sd = F.mean(0), F.std(0) + 1e-12
    Fs = (F - mu) / sd
    # Eigen-decomposition of the Gram matrix: the same spectrum as an SVD, much cheaper for n >> p.
    evals, V = np.linalg.eigh(Fs.T @ Fs)
    s = np.sqrt(np.maximum(evals, 0.0))
    keep = s > 1e-8 * s.max()
    s, V = s[keep], V[:, keep]
    Vt = V.T
    Ur = (Vt @ (Fs.T @ (r - r.mean()))) / s
    n = F.shape[0]
    best = None
    for lam in np.geomspace(1e-3, 1e4, 22) * n / 100:
        f = s**2 / (s**2 + lam)
        resid = np.sum(((1 - f) * Ur) ** 2) + np.sum((r - r.mean()) ** 2) - np.sum(Ur**2)
        gcv = resid / (1 - f.sum() / n) ** 2
        if best is None or gcv < best[0]:
            best = (gcv, lam)
    lam = best[1]
    beta = Vt.T @ (s / (s**2 + lam) * Ur)
    return beta / sd, mu, float(r.mean())


def blackbox_check(preps, pool_idx_folds: list[np.ndarray], fitted: FittedModel, cfg: SelectionConfig,
                   seed: int = 0, model: Model | None = None) -> dict:
    """Held-out R² of a flexible regressor on the final model's one-step residual.

    Cross-fitted over the folds. ``unexplained_structure`` is set when the pooled held-out R²
    is at least ``bb_min_r2`` and a Wilcoxon test over held-out episodes (squared error
    against the training mean vs the regressor) gives p < ``bb_alpha``. A model with
    ``residual_rows(prep, fitted) -> (features, residual)`` (:class:`ResidualRows`) supplies its own
    rows; otherwise the axis model's equation-error residual is used.
    """
    rows = {}
    custom = isinstance(model, ResidualRows)
    for fold in pool_idx_folds:
        for j in fold:
            p = preps[j]
            if custom:
                rows[j] = model.residual_rows(p, fitted)
                continue
            X, y, k = axis.design(p, fitted.params)
            theta = np.array([fitted.params.coef[n] for n in axis.coef_names(fitted.params.effects)])
            v = axis.state_velocity(p, fitted.params.sensor)
            rows[j] = (_bb_features(p, k, v), y - X @ theta)
    # Axis: position gets fine bins (position-dependent forces such as cogging are the typical
    # out-of-catalogue effect), velocity medium, command lags and the rest coarse. Short
    # multi-channel episodes (a few hundred rows in all): coarse bins everywhere.
    d = next(iter(rows.values()))[0].shape[1]
    n_bins = [8] * d if custom else ([120, 40] + [24] * d)[:d]
    allz = np.concatenate([z for z, _ in rows.values()])
    zmu, zsd = allz.mean(0), allz.std(0) + 1e-12
    sse_null, sse_bb = [], []
    for i, held in enumerate(pool_idx_folds):
        train = [j for f, fold in enumerate(pool_idx_folds) if f != i for j in fold]
        Z = np.concatenate([rows[j][0] for j in train])
        R = np.concatenate([rows[j][1] for j in train])
        stride = max(1, Z.shape[0] // 3000)  # bound the cost on long 1 kHz logs
        Zs = (Z[::stride] - zmu) / zsd
        edges = [np.unique(np.quantile(Zs[:, j], np.linspace(0, 1, nb + 1)[1:-1]))
                 for j, nb in enumerate(n_bins)]
        bins_only = () if custom else (0,)  # axis: column 0 is the position
        F = _bb_basis(Zs, edges, seed, bins_only)
        beta, fmu, rmean = _ridge_gcv(F, R[::stride])
        for j in held:
            z, r = rows[j]
            pred = rmean + (_bb_basis((z - zmu) / zsd, edges, seed, bins_only) - fmu) @ beta
            sse_null.append(float(np.sum((r - rmean) ** 2)))
            sse_bb.append(float(np.sum((r - pred) ** 2)))
    sse_null, sse_bb = np.asarray(sse_null), np.asarray(sse_bb)
    r2 = float(1.0 - sse_bb.sum() / sse_null.sum())
    p = paired_p(sse_null, sse_bb)
    return {
        "method": "ridge (GCV) on per-input quantile-bin indicators + random Fourier features of "
                  + ("commands (now, one period before) and the replay's predicted speeds; target: one-step "
                     "increment residual of v_fwd and crank velocities" if custom else
                     "lagged command, position (bins only), velocity") + "; cross-fitted over the folds",
        "heldout_r2": r2,
        "p_value": p,
        "threshold_r2": cfg.bb_min_r2,
        "alpha": cfg.bb_alpha,
        "unexplained_structure": bool(r2 >= cfg.bb_min_r2 and p < cfg.bb_alpha),
    }


# ----------------------------------------------------------------------------- detection limit


def _autocorr_inflation(r: np.ndarray, max_lag: int) -> float:
    """Long-run variance factor 1 + 2·Σρ_k (Bartlett weights) of a residual series, ≥ 1."""
    r = r - r.mean()
    var = float(r @ r) / r.size
    if var <= 0:
        return 1.0
    tot = 1.0
    for k in range(1, max_lag + 1):
        rho = float(r[:-k] @ r[k:]) / (r.size * var)
        tot += 2 * (1 - k / (max_lag + 1)) * rho
    return max(1.0, tot)


def detection_limits(preps_pool: list[axis.Prepared], fitted: FittedAxis, candidates: list[str],
                     skipped: dict[str, str], cfg: SelectionConfig) -> dict:
    """Smallest value of each effect's primary parameter the data could have revealed.

    The effect's regressor (its column, or for nonlinear effects the derivative of the model
    acceleration with respect to its parameter at the no-effect value) is projected off the
    model's own regressors (the nominal refit would absorb that part), and
    limit = (z_{1−α/(2m)} + z_power) · σ_eff / ‖projected regressor‖, with σ_eff the residual
    standard deviation inflated for autocorrelation (long-run variance).
    """
    params = fitted.params
    names = axis.coef_names(params.effects)
    theta = np.array([params.coef[n] for n in names])
    Xs, res = [], []
    for p in preps_pool:
        X, y, _ = axis.design(p, params)
        Xs.append(X)
        res.append(y - X @ theta)
    X0 = np.concatenate(Xs)
    r = np.concatenate(res)
    infl = _autocorr_inflation(res[0] if len(res[0]) > 50 else r, 2 * preps_pool[0].window)
    sigma = float(np.std(r)) * math.sqrt(infl)
    # "moderate": a 95 % interval of the effect that excludes no effect, with the given power
    z = st.norm.ppf(1 - cfg.moderate_quantile) + st.norm.ppf(cfg.power)
    Q, _ = np.linalg.qr(X0)
    out: dict[str, dict] = {}
    for name in list(candidates) + [s for s in skipped if s not in candidates]:
        spec = CATALOGUE[name]
        entry = {"param": spec.primary, "unit": spec.unit, "value": None}
        if name in skipped:
            entry["note"] = skipped[name]
            out[name] = entry
            continue
        if name in params.effects:
            entry["note"] = "accepted; see its bootstrap interval"
            out[name] = entry
            continue
        col, note = _sensitivity(preps_pool, params, name)
        if col is None:
            entry["note"] = note
            out[name] = entry
            continue
        resid = col - Q @ (Q.T @ col)
        nrm = float(np.linalg.norm(resid))
        if nrm < 1e-12 * (np.linalg.norm(col) + 1e-300):
            entry["note"] = "not separable from the terms already in the model with this data (a look-alike is accepted)"
        else:
            entry["value"] = float(z * sigma / nrm)
            entry["note"] = note
        out[name] = entry
    return {"per_effect": out, "sigma_eff": sigma, "autocorr_inflation": infl, "z": float(z)}


def _sensitivity(preps, params: axis.AxisParams, name: str) -> tuple[np.ndarray | None, str]:
    """d(model acceleration)/d(primary parameter) at the no-effect value, stacked over episodes."""
    import copy

    spec = CATALOGUE[name]
    if name in ("sensor_bias", "sensor_scale"):
        return None, "velocity-sensor effects are estimated by direct regression; see sensor fit"
    if name == "saturation":
        return None, "a clip above the largest logged |u| is invisible; see the command range in data"
    if name == "cogging":
        return None, "its period is searched over many values; the black-box check covers position-periodic loads"
    if name in axis.HYPER_OF and axis.HYPER_OF[name] in axis.OUTPUT_HYPERS:
        return None, ("acts on the measured position only (open-loop windows), not on the one-step acceleration: "
                      "no local estimate; it shows as a position step of twice the play at each motion reversal")
    cols = []
    for p in preps:
        X0, _, _ = axis.design(p, params)
        theta = np.array([params.coef[n] for n in axis.coef_names(params.effects)])
        if name in axis.COEF_OF:
            q = copy.deepcopy(params)
            q.effects = params.effects + [name]
            if name == "stribeck_friction":
                q.hyper["vs"] = float(np.sqrt(np.mean(p.v_obs**2))) * 0.1
            if name == "gravity_load":
                q.hyper["q0_rad"] = 0.0
            X1, _, _ = axis.design(p, q)
            col = X1[:, -1] if name != "battery_sag" else X1[:, axis.coef_names(q.effects).index("kb")] * params.coef["a"]
            cols.append(col)
            continue
        h = axis.HYPER_OF[name]
        q = copy.deepcopy(params)
        q.effects = params.effects + [name]
        step = {"delay_s": 0.25 * p.period_s, "tau_s": 0.25 * p.period_s}.get(h)
        if step is None:
            au = np.abs(p.ep.u)
            step = 0.01 * float(np.quantile(au, 0.9)) if h != "mu_per_unit" else 0.01
        q.hyper[h] = spec.no_effect + step
        X1, _, _ = axis.design(p, q)
        cols.append((X1[:, : X0.shape[1]] @ theta - X0 @ theta) / step)
    return np.concatenate(cols), "first-order (local) estimate at the no-effect value"
