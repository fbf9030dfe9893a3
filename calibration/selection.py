"""Effect selection: folds, locked test set, paired tests, bootstrap, look-alikes, black box.

Procedure (see docs/calibration.md):

1. Whole episodes are split into a locked test set (never used for any decision) and a
   training pool, which is split into K folds.
2. Each round, every remaining candidate is added to the accepted set; model + candidate are
   fit on K−1 folds and scored on the held-out fold (one-step and multi-step open-loop), so
   every training episode gets a held-out loss with and without the candidate.
3. A candidate is accepted when (a) a one-sided Wilcoxon signed-rank test over held-out
   episodes says it lowers the loss, at α / (number of candidates in the round); (b) the
   relative held-out gain is at least ``min_gain``; (c) the 95 % episode-bootstrap interval
   of its primary parameter excludes the no-effect value; (d) it improves the out-of-bag loss
   in at least ``min_stability`` of the bootstrap replicates. The best such candidate is
   accepted, its look-alikes that explain the data about as well are reported as ambiguous,
   and the round repeats until nothing passes.
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
from hilstack.calibration.models import FittedAxis, FittedModel, Model


@dataclass(frozen=True)
class SelectionConfig:
    """Statistical settings (defaults are those used in docs/calibration.md)."""

    k_folds: int = 5
    test_fraction: float = 0.2
    alpha: float = 0.05
    min_gain: float = 0.02  # relative reduction of the held-out loss
    n_boot: int = 40
    min_stability: float = 0.8
    horizon_s: float = 1.0
    min_episodes: int = 20
    max_rounds: int = 6
    bb_alpha: float = 0.01
    bb_min_r2: float = 0.05
    power: float = 0.8


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


def split_episodes(n: int, cfg: SelectionConfig, seed: int,
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


def crossval_losses(model: Model, preps, folds, effects, nm, horizon: int,
                    start: FittedModel | None, search: list[str] | None) -> np.ndarray:
    """Held-out loss of every training-pool episode (pool order = concatenated folds)."""
    out = []
    for i, held in enumerate(folds):
        train = [preps[j] for f, fold in enumerate(folds) if f != i for j in fold]
        fitted = model.fit(train, effects, refine=False, start=start, search=search)
        out.extend(model.episode_loss(preps[j], fitted, horizon, nm) for j in held)
    return np.asarray(out)


def _excludes(interval: list[float], no_effect: float) -> bool:
    lo, hi = interval
    if math.isinf(no_effect):
        return math.isfinite(hi)
    return lo > no_effect or hi < no_effect


def bootstrap_effect(model: Model, preps, pool_idx: np.ndarray, base: FittedModel, effects: list[str],
                     name: str, n_boot: int, seed: int, nm) -> tuple[list[float], float, list[float]]:
    """Episode bootstrap of the candidate's primary parameter and its out-of-bag stability.

    Returns (95 % interval, fraction of replicates whose out-of-bag one-step loss improves, values).
    """
    rng = np.random.default_rng(seed + 7919)
    pool = [preps[i] for i in pool_idx]
    vals, wins, tried = [], 0, 0
    # A position-periodic load is measured along the phase of its fit on the whole pool, so a
    # replicate cannot flip its sign by moving to the other representation of the same load.
    ref = (model.fit(pool, effects + [name], refine=False, start=base, search=[name])
           if hasattr(base, "primary_along") and name in axis.PHASE_OF else None)
    for _ in range(n_boot):
        counts = np.bincount(rng.integers(0, len(pool), len(pool)), minlength=len(pool)).astype(float)
        b = model.fit(pool, effects, weights=counts, refine=False, start=base, search=[])
        c = model.fit(pool, effects + [name], weights=counts, refine=False, start=base, search=[name])
        vals.append(c.primary(name) if ref is None else c.primary_along(name, ref))
        oob = np.flatnonzero(counts == 0)
        if oob.size:
            tried += 1
            lb = np.sum([np.atleast_1d(model.oob_loss(pool[i], b, nm)) for i in oob], axis=0)
            lc = np.sum([np.atleast_1d(model.oob_loss(pool[i], c, nm)) for i in oob], axis=0)
            wins += heldout_gain(lb[None], lc[None]) > 0
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
    folds: list[np.ndarray]
    norms: Norms
    horizon: int


def select_effects(model: Model, preps: list[axis.Prepared], cfg: SelectionConfig, seed: int = 0,
                   log: Callable[[str], None] = lambda s: None) -> SelectionResult:
    """Greedy forward selection of effects with held-out evidence (see module docstring)."""
    locked = np.array([bool(getattr(getattr(p, "ep", None), "meta", {}).get("locked_test")) for p in preps])
    test_idx, folds = split_episodes(len(preps), cfg, seed, locked)
    pool_idx = np.concatenate(folds)
    pool = [preps[i] for i in pool_idx]
    nm = model.norms(pool)
    horizon = max(2, int(round(cfg.horizon_s / preps[0].period_s)))
    if isinstance(nm, Norms):
        nm.horizon = horizon
    candidates, skipped = model.candidate_effects(preps)
    log(f"{len(preps)} episodes: {test_idx.size} locked for test, {pool_idx.size} in {len(folds)} folds; "
        f"{len(candidates)} candidate effects")

    nominal = model.fit(pool, [])
    current = nominal
    accepted: list[CandidateResult] = []
    ambiguous: list[dict] = []
    rounds: list[dict] = []
    # Fold indices into `preps` order; losses come out in pool order.
    budget = 0  # index of the last error budget spent (a pair attempt spends the next round's)
    for rnd in range(cfg.max_rounds):
        if budget >= cfg.max_rounds:
            break
        budget += 1
        effects = list(current.effects)
        candidates, skipped = model.candidate_effects(preps, tuple(effects))
        remaining = [c for c in candidates if c not in effects]
        if not remaining:
            break
        base_loss = crossval_losses(model, preps, folds, effects, nm, horizon, current, [])
        alpha_round = round_alpha(cfg.alpha, budget) / len(remaining)
        results = []
        for name in remaining:
            losses = crossval_losses(model, preps, folds, effects + [name], nm, horizon, current, [name])
            gain = heldout_gain(base_loss, losses)
            r = CandidateResult(name, losses, gain, paired_p(base_loss, losses))
            results.append(r)
            log(f"  round {rnd + 1}: {name:18s} held-out gain {gain:+.3f}  p={r.p_value:.2g}")
        results.sort(key=lambda r: -r.gain)
        passing = [r for r in results if r.p_value < alpha_round and r.gain >= cfg.min_gain]
        round_doc = {
            "round": rnd + 1,
            "budget_round": budget,
            "base_effects": effects,
            "base_heldout_loss": base_loss.mean(axis=0).tolist() if base_loss.ndim > 1 else float(base_loss.mean()),
            "alpha": alpha_round,
            "candidates": [{"name": r.name, "heldout_gain": r.gain, "p_value": r.p_value} for r in results],
        }
        if base_loss.ndim > 1:
            round_doc["loss_channels"] = list(LOSS_CHANNELS)
            for c, r in zip(round_doc["candidates"], results, strict=True):
                c["channel_gain"] = (1.0 - r.losses.sum(0) / base_loss.sum(0)).tolist()
        # Look-alikes: test each of the best candidates in the presence of the others, so that one
        # that only mimics the true effect (a deadband for Coulomb friction) cannot block it.
        pairs = (pair_tests(model, preps, folds, effects, nm, horizon, current, results, alpha_round, cfg)
                 if getattr(model, "pair_tests", False) else [])
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
            stuck = {}
            if getattr(model, "reports_bounds", False):
                bound = model.fit(pool, effects + [r.name], refine=False, start=current, search=[r.name])
                stuck = {h: v for h, v in bound.at_bound.items() if h == axis.HYPER_OF.get(r.name)}
            if stuck:
                r.verdict = (f"rejected: estimate at the edge of its search range even after widening it "
                             f"({', '.join(f'{h}={v:.4g}' for h, v in stuck.items())}); the data do not bound it")
                log(f"  round {rnd + 1}: {r.name}: {r.verdict}")
                continue
            r.interval, r.stability, r.boot_values = bootstrap_effect(
                model, preps, pool_idx, current, effects, r.name, cfg.n_boot, seed + rnd, nm)
            ok_int = _excludes(r.interval, model.catalogue[r.name].no_effect)
            ok_stab = r.stability >= cfg.min_stability
            r.verdict = "accepted" if ok_int and ok_stab else (
                "rejected: bootstrap interval includes the no-effect value" if not ok_int
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
        # Pair fallback: only when the best single candidate shows evidence on its own (unadjusted)
        # and a round of error budget is left for it.
        lead = results[0] if results else None
        if (winner is None and getattr(model, "pair_tests", False) and len(results) > 1 and budget < cfg.max_rounds
                and lead.gain >= cfg.min_gain and lead.p_value < cfg.alpha):
            budget += 1
            pair = try_pair(model, preps, folds, pool_idx, effects, nm, horizon, current, results, base_loss,
                            round_alpha(cfg.alpha, budget) / (len(results) - 1), cfg, seed + rnd, round_doc, log)
            if pair:
                current = model.fit(pool, effects + [r.name for r in pair], refine=True, start=current)
                for r in pair:
                    r.fitted = current
                    accepted.append(r)
                log(f"accepted the pair {pair[0].name} + {pair[1].name}")
                continue
        if winner is None:
            break
        # Look-alikes that explain the held-out data about as well as the winner.
        table = model.look_alikes
        for r in passing:
            if r is winner or not is_look_alike(winner.name, r.name, table):
                continue
            p_sep = paired_p(r.losses, winner.losses)
            if p_sep >= cfg.alpha:
                excitation = separating_excitation(winner.name, r.name, table)
                ambiguous.append({
                    "effects": [winner.name, r.name],
                    "chosen": winner.name,
                    "heldout_gain": {winner.name: winner.gain, r.name: r.gain},
                    "p_value_separation": p_sep,
                    "excitation": excitation,
                })
                log(f"  ambiguous: {winner.name} vs {r.name} (p={p_sep:.2g}); separate with {excitation}")
        prev = current
        current = model.fit(pool, effects + [winner.name], refine=True, start=current)
        if getattr(model, "shift_interval_to_refined", False):
            # The bootstrap re-fits on the cached grid (no new replays); the refined pool fit
            # replays off-grid. Centre the percentile interval on the refined estimate: shift it
            # by (refined − grid estimate on the same pool), the grid's interpolation bias.
            plain = model.fit(pool, effects + [winner.name], refine=False, start=prev, search=[winner.name])
            delta = current.primary(winner.name) - plain.primary(winner.name)
            winner.interval = [winner.interval[0] + delta, winner.interval[1] + delta]
        winner.fitted = current
        accepted.append(winner)
        log(f"accepted {winner.name}: {current.effect_params(winner.name)}")
    if len(accepted) > 1:
        current, accepted, ambiguous = prune_effects(model, preps, folds, pool, current, accepted, ambiguous, nm,
                                                     horizon, cfg, rounds, log)
    if accepted and getattr(model, "pair_tests", False):
        ambiguous += swap_look_alikes(model, preps, folds, current, accepted, ambiguous, nm, horizon, cfg, log)
    if not accepted:
        log("no effect passed the tests")
    return SelectionResult(accepted, ambiguous, rounds, current, nominal, skipped, test_idx, folds, nm, horizon)


def try_pair(model, preps, folds, pool_idx, effects, nm, horizon, current, results: list[CandidateResult],
             base_loss, alpha_pair: float, cfg: SelectionConfig, seed: int, round_doc: dict, log):
    """When no single candidate passes: the best one together with each other candidate.

    Tried only when the best candidate helps on its own at the unadjusted level (gain ≥
    ``min_gain``, p < alpha) and a round of error budget is left.

    Two effects may only help together (on EMPS, Coulomb friction alone makes some open-loop
    windows worse; with the force offset it explains the data). The pair is tested against the
    model without both, at the next round's error budget split over the pairs tried (so the
    error rate stays controlled over all rounds), and each member must also help in the
    presence of the other (p < alpha) and pass the bootstrap checks with the other in the model.
    Returns the two accepted CandidateResults, or None.
    """
    lead = results[0]
    tried, best = [], None
    for other in results[1:]:
        both = crossval_losses(model, preps, folds, effects + [lead.name, other.name], nm, horizon, current,
                               [lead.name, other.name])
        gain, p = heldout_gain(base_loss, both), paired_p(base_loss, both)
        p_lead, p_other = paired_p(other.losses, both), paired_p(lead.losses, both)
        tried.append({"effects": [lead.name, other.name], "heldout_gain": gain, "p_value": p,
                      "p_adding": {lead.name: p_lead, other.name: p_other}})
        if (p < alpha_pair and gain >= cfg.min_gain and max(p_lead, p_other) < cfg.alpha
                and (best is None or gain > best[1])):
            best = (other, gain, p, both)
    round_doc["pair_fallback"] = {"alpha": alpha_pair, "tried": tried}
    if best is None:
        return None
    other, gain, p, _ = best
    out = []
    for r, partner in ((lead, other), (other, lead)):
        res = CandidateResult(r.name, best[3], gain, p)
        res.interval, res.stability, res.boot_values = bootstrap_effect(
            model, preps, pool_idx, current, effects + [partner.name], r.name, cfg.n_boot, seed, nm)
        ok = _excludes(res.interval, model.catalogue[r.name].no_effect) and res.stability >= cfg.min_stability
        res.verdict = "accepted (as a pair with " + partner.name + ")" if ok else "rejected: pair member fails the bootstrap"
        log(f"  pair {lead.name} + {other.name}: {r.name} interval {res.interval}, stability {res.stability:.2f}")
        out.append(res)
    round_doc["pair_fallback"]["decision"] = [{"name": r.name, "verdict": r.verdict, "interval": r.interval,
                                               "stability": r.stability} for r in out]
    return out if all(r.verdict.startswith("accepted") for r in out) else None


def swap_look_alikes(model, preps, folds, current, accepted, ambiguous, nm, horizon, cfg, log) -> list[dict]:
    """Swap each accepted effect for each of its look-alikes that was never compared on equal terms.

    The order of acceptance can hide a look-alike: once Coulomb friction and an offset are in,
    direction-dependent friction (the same thing on every moving row) adds nothing and is never
    a rival. Each accepted effect is replaced by each look-alike that the model with the others
    offers; when the held-out data cannot tell the two models apart (paired tests both ways,
    p ≥ alpha), the pair is reported as ambiguous with the excitation that would separate it.
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
            p_worse, p_better = paired_p(swapped, full), paired_p(full, swapped)
            if min(p_worse, p_better) >= cfg.alpha:
                excitation = separating_excitation(name, alt, table)
                out.append({"effects": [name, alt], "chosen": name,
                            "heldout_gain": {name: 0.0, alt: heldout_gain(full, swapped)},
                            "p_value_separation": min(p_worse, p_better), "excitation": excitation,
                            "found_by": "swap"})
                known.add(frozenset({name, alt}))
                log(f"  ambiguous (swap): {name} vs {alt}; separate with {excitation}")
    return out


def prune_effects(model, preps, folds, pool, current, accepted, ambiguous, nm, horizon, cfg, rounds, log):
    """Backward check: drop an accepted effect that the later ones made redundant.

    Greedy forward selection can accept a look-alike first (an offset before the slope and the
    payload that explain it). Each accepted effect is removed in turn; if the held-out loss
    without it is not clearly worse (paired p ≥ alpha or gain < ``min_gain``), it goes.
    """
    full = crossval_losses(model, preps, folds, list(current.effects), nm, horizon, current, [])
    dropped = []
    for r in list(accepted):
        rest = [e for e in current.effects if e != r.name]
        without = crossval_losses(model, preps, folds, rest, nm, horizon, current, [])
        p, gain = paired_p(without, full), heldout_gain(without, full)
        if p >= cfg.alpha or gain < cfg.min_gain:
            log(f"pruned {r.name}: the other accepted effects explain it (gain of keeping it {gain:+.3f}, p={p:.2g})")
            dropped.append({"name": r.name, "gain_of_keeping": gain, "p_value": p})
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


def round_alpha(alpha: float, rnd: int) -> float:
    """Error budget of round ``rnd`` (1-based): alpha·6/(π²·rnd²), which sums to alpha over all rounds.

    Within a round it is split evenly over the candidates (Bonferroni), so the probability of
    accepting any effect that is not there stays below ``alpha`` over the whole selection,
    however many rounds it takes.
    """
    return alpha * 6.0 / (math.pi**2 * rnd**2)


#: How many of a round's best candidates are tested in each other's presence.
PAIR_TOP = 3


def pair_tests(model, preps, folds, effects, nm, horizon, current, results: list[CandidateResult],
               alpha_round: float, cfg: SelectionConfig) -> list[dict]:
    """Test the best candidates of a round in the presence of each other.

    For the top :data:`PAIR_TOP` candidates that help on their own (gain ≥ ``min_gain``,
    unadjusted p < alpha), fit every pair (a, b)
    together. "a explains b" when adding a to b still lowers the held-out loss (p < the round's
    alpha, gain ≥ ``min_gain``) while adding b to a does not (p ≥ alpha or gain < ``min_gain``):
    b then only mimics part of a. Returns one record per pair.
    """
    top = [r for r in results if r.gain >= cfg.min_gain and r.p_value < cfg.alpha][:PAIR_TOP]
    out = []
    for i in range(len(top)):
        for j in range(i + 1, len(top)):
            a, b = top[i], top[j]
            both = crossval_losses(model, preps, folds, effects + [a.name, b.name], nm, horizon, current,
                                   [a.name, b.name])
            a_adds = (paired_p(b.losses, both), heldout_gain(b.losses, both))
            b_adds = (paired_p(a.losses, both), heldout_gain(a.losses, both))

            def helps(t):
                return t[0] < alpha_round and t[1] >= cfg.min_gain

            def useless(t):
                return t[0] >= cfg.alpha or t[1] < cfg.min_gain

            # gain_adding[a]: held-out gain of adding a to a model that already has b (and vice versa)
            rec = {"effects": [a.name, b.name], "gain_adding": {a.name: a_adds[1], b.name: b_adds[1]},
                   "p_adding": {a.name: a_adds[0], b.name: b_adds[0]}, "explains": None, "explained": None}
            if helps(a_adds) and useless(b_adds):
                rec["explains"], rec["explained"] = a.name, b.name
            elif helps(b_adds) and useless(a_adds):
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
    ``residual_rows(prep, fitted) -> (features, residual)`` supplies its own rows; otherwise
    the axis model's equation-error residual is used.
    """
    rows = {}
    custom = model is not None and hasattr(model, "residual_rows")
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
    m = max(1, len(candidates))
    # the first round's per-candidate threshold: the level an effect of this size would have to pass
    z = st.norm.ppf(1 - round_alpha(cfg.alpha, 1) / (2 * m)) + st.norm.ppf(cfg.power)
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
