"""The ``axis`` nominal model: a single-axis drive, identified in normalized form.

Physics: J·dv/dt = k_u·u − b·v, dx/dt = v. Without a known force, J cannot be separated
from k_u (scaling both leaves the motion unchanged), so the model is identified as

    dv/dt = g·(a·ũ − c·v − fc·sgn(v) − fs·exp(−(v/vs)²)·sgn(v) + d) + s_g

with a = k_u/J [x/s² per u], c = b/J [1/s], fc, fs, d forces over J [x/s²], s_g a gravity
acceleration (slope), g = 1/(1 + mu·m) the payload factor and ũ the command after the
input-side effects (delay → saturation → deadband → backlash → battery scaling → lag).
When the caller knows k_u (e.g. EMPS: gtau = 35.15 N/V), physical values are reported too:
J = k_u/a, b = c·J, Fc = fc·J, offset = d·J.

Identification is equation error on the sampled velocity: y_k = (v_{k+1} − v_k)/Δt against
the features at k. All coefficients (a, c, fc, fs, d, s_g, battery gain) enter linearly; the
remaining effect parameters (delay, lag, deadband width, ...) are found by a grid search
with linear least squares inside, refined by a bounded scalar search. The nominal a and c
are refit with every candidate effect, so a mistuned gain or viscous term is never
reported as an effect. When velocity is derived from position with the Savitzky-Golay
derivative, the command features are passed through the same zero-phase kernel so that the
smoothing is not mistaken for a lag.

Discretization: ZOH commands; ũ_k is the average force over [t_k, t_k+1) (exact for delay and
lag); the simulator integrates friction implicitly (stick when |v + Δt·F| ≤ Δt·f_fric), so
it holds still under Coulomb friction without chattering.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from hilstack.calibration import compiled
from hilstack.calibration.compiled import COEF_COLUMNS
from hilstack.calibration.data import Recording, default_sg_window, sg_velocity, sg_velocity_kernel
from hilstack.calibration.effects import CATALOGUE

#: Hyper-parameters (nonlinear) per effect, and linear coefficients per effect.
HYPER_OF: dict[str, str] = {
    "delay": "delay_s",
    "actuator_lag": "tau_s",
    "deadband": "width_u",
    "backlash": "halfwidth_u",
    "load_backlash": "halfwidth_x",
    "saturation": "limit_u",
    "stribeck_friction": "vs",
    "payload_mass": "mu_per_unit",
    "gravity_load": "q0_rad",
    "cogging": "cog_k",
}
COEF_OF: dict[str, str] = {
    "coulomb_friction": "fc_acc",
    "stribeck_friction": "fs_extra_acc",
    "force_offset": "offset_acc",
    "slope": "gravity_acc",
    "battery_sag": "kb",
    "back_emf": "kemf",
    "asymmetric_friction": "fa_acc",
    "gravity_load": "gl_acc",
    "cogging": "gc_acc",
}
NOMINAL_COEFS = ("a", "c_per_s")
#: The phase hyper-parameter of each position-periodic load (see :meth:`AxisParams.primary_along`).
PHASE_OF = {"gravity_load": "q0_rad", "cogging": "cog_phase"}
#: Hyper-parameters of the output side: they change the open-loop replay, not the one-step
#: regression (load-side play: the load stands still in the gap, and standstill rows are not
#: regression rows), so they are fit on open-loop windows of this length [s].
OUTPUT_HYPERS = ("halfwidth_x",)
OUTPUT_FIT_HORIZON_S = 0.5
SENSOR_EFFECTS = ("sensor_bias", "sensor_scale")
HYPER_NO_EFFECT = {
    "delay_s": 0.0,
    "tau_s": 0.0,
    "width_u": 0.0,
    "halfwidth_u": 0.0,
    "halfwidth_x": 0.0,
    "limit_u": math.inf,
    "vs": 1.0,
    "mu_per_unit": 0.0,
    "q0_rad": 0.0,
    "cog_k": 1.0,
    "cog_phase": 0.0,
}


# ----------------------------------------------------------------------------- prepared data


@dataclass
class Prepared:
    """An episode with the derived signals the axis model needs (computed once)."""

    ep: Recording
    period_s: float
    v_obs: np.ndarray  # the observed velocity channel [x/s]: measured, or SG-derived from x
    v_from_x: np.ndarray  # SG derivative of position [x/s] (reference for velocity sensor checks)
    kernel: np.ndarray | None  # zero-phase kernel applied by the velocity estimate (None: measured)
    margin: int  # samples dropped at both ends (filter edges, longest delay tested)
    window: int  # Savitzky-Golay window [samples]
    moving: np.ndarray  # bool per sample: regression rows (the axis moves; see moving_mask)
    v_min: float  # velocity [x/s] below which the axis counts as stopped
    #: regression statistics per model configuration (see :func:`episode_stats`)
    stats_cache: dict = field(default_factory=dict, repr=False, compare=False)
    #: feature columns per hyper-parameter values (see :func:`raw_features`)
    feature_cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def n(self) -> int:
        return self.ep.n


def prepare(episodes: list[Recording], sg_window: int | None = None, max_delay_s: float | None = None) -> list[Prepared]:
    """Derive velocities for all episodes (same SG window for all: they share a period)."""
    period_s = float(np.median([e.period_s for e in episodes]))
    window = sg_window or default_sg_window(period_s)
    max_delay = max_delay_samples(period_s) if max_delay_s is None else int(math.ceil(max_delay_s / period_s))
    kernel = sg_velocity_kernel(window)
    use_logged = logged_velocity_usable(episodes, period_s, window)
    out = []
    for e in episodes:
        v_x = sg_velocity(e.x, period_s, window)
        measured = e.v_meas is not None and use_logged
        v_obs = e.v_meas if measured else v_x
        moving, v_min = moving_mask(e, v_obs, period_s, window, measured)
        # The command before the first sample is unknown; the input chain assumes it equals the
        # first one. That holds for an episode that starts at rest with a steady command, so such an
        # episode keeps its first samples (the step-from-rest response shows delay and lag); a
        # segment cut from a longer recording, or an episode already moving, loses the longest
        # delay tested at its start.
        cut = "segment_of" in e.meta or bool(np.any(np.abs(v_obs[: window]) > v_min)) \
            or bool(np.ptp(e.u[: window]) > 0)
        out.append(
            Prepared(
                ep=e,
                period_s=period_s,
                v_obs=v_obs,
                v_from_x=v_x,
                kernel=None if measured else kernel,
                margin=window // 2 + 2 + (max_delay if cut else 0),
                window=window,
                moving=moving,
                v_min=v_min,
            )
        )
    return out


def segment_margin(period_s: float, sg_window: int | None = None) -> int:
    """Samples a segment of a long recording loses at each end (see :func:`prepare`)."""
    window = sg_window or default_sg_window(period_s)
    return window // 2 + 2 + max_delay_samples(period_s)


#: A logged velocity noisier than this many times the Savitzky-Golay derivative of position is
#: not used as the state (quantised encoder differences, see :func:`logged_velocity_usable`).
MAX_LOGGED_VELOCITY_NOISE_RATIO = 3.0


def logged_velocity_usable(episodes: list[Recording], period_s: float, window: int) -> bool:
    """Whether the logged velocity channel is fit to be the model's velocity state.

    Many drives log velocity as the finite difference of a quantised encoder: steps of
    resolution/period, far noisier than a smoothed derivative of the same position. Used as the
    state, such a channel puts its noise into the regressors (an errors-in-variables bias of every
    coefficient) and into the one-step target. When its noise (median over episodes) exceeds
    :data:`MAX_LOGGED_VELOCITY_NOISE_RATIO` times that of the Savitzky-Golay derivative of
    position, the derivative is used instead (``velocity_source`` in the report says so).
    """
    logged = [e for e in episodes if e.v_meas is not None]
    if not logged:
        return False
    ratios = [velocity_noise(e, period_s, window, True, robust=True)
              / max(velocity_noise(e, period_s, window, False, robust=True), 1e-300) for e in logged]
    return float(np.median(ratios)) <= MAX_LOGGED_VELOCITY_NOISE_RATIO


def velocity_noise(e: Recording, period_s: float, window: int, measured: bool, robust: bool = False) -> float:
    """Noise std [x/s] of the velocity channel: from the SG residual of the logged signal."""
    from scipy.signal import savgol_coeffs, savgol_filter

    sig = e.v_meas if measured else e.x
    r = sig - savgol_filter(sig, window, 2, mode="interp")
    # robust: the median absolute deviation ignores the kinks of a velocity at command steps
    spread = 1.4826 * float(np.median(np.abs(r - np.median(r)))) if robust else float(np.std(r))
    sigma = spread * math.sqrt(window / max(window - 3, 1))
    if measured:
        return sigma
    d = savgol_coeffs(window, 2, deriv=1, delta=period_s, use="dot")
    return sigma * float(np.linalg.norm(d))


def moving_mask(e: Recording, v: np.ndarray, period_s: float, window: int,
                measured: bool | None = None) -> tuple[np.ndarray, float]:
    """Samples used as regression rows: the axis moves, away from stops by a smoothing window.

    While the axis sticks, Coulomb friction is whatever balances the other forces, so an
    equation-error row there says nothing about the friction level; around a stop the
    smoothed velocity is smeared over the window. Both are left out of the regression (for
    every candidate alike: the mask depends on data only); the simulator still covers them.
    """
    measured = e.v_meas is not None if measured is None else measured
    v_min = 3.0 * velocity_noise(e, period_s, window, measured) + 1e-3 * float(np.sqrt(np.mean(v**2)))
    slow = np.abs(v) < v_min
    # A fast reversal can jump over the threshold between two samples: mark sign changes too.
    flip = np.signbit(v[1:]) != np.signbit(v[:-1])
    slow[:-1] |= flip
    slow[1:] |= flip
    m = window // 2 + 1
    if slow.any():
        slow = np.convolve(slow.astype(float), np.ones(2 * m + 1), mode="same") > 0
    return ~slow, v_min


def max_delay_samples(period_s: float) -> int:
    """Longest delay searched [samples]: 150 ms, at least 8 and at most 60 samples."""
    return int(min(60, max(8, round(0.15 / period_s))))


def _smooth(p: Prepared, a: np.ndarray) -> np.ndarray:
    if p.kernel is None:
        return a
    m = len(p.kernel) // 2
    padded = np.concatenate([np.full(m, a[0]), a, np.full(m, a[-1])])
    return np.convolve(padded, p.kernel, mode="valid")


# ----------------------------------------------------------------------------- input chain


def backlash_play(u: np.ndarray, halfwidth: float) -> np.ndarray:
    """Play (backlash) operator: output follows u only once u moved ``halfwidth`` past it."""
    if halfwidth <= 0:
        return u.copy()
    if compiled.backlash_play is not None and USE_COMPILED:
        return compiled.backlash_play(np.ascontiguousarray(u, dtype=float), float(halfwidth))
    # Pure-python floats: ~20x faster than indexing numpy scalars in a sequential loop.
    out = []
    prev = float(u[0])
    for uk in u.tolist():
        lo, hi = uk - halfwidth, uk + halfwidth
        prev = lo if prev < lo else (hi if prev > hi else prev)
        out.append(prev)
    y = np.asarray(out)
    return y


def input_chain(u: np.ndarray, period_s: float, hp: dict[str, float],
                scale: np.ndarray | None = None) -> np.ndarray:
    """Command → average force per interval (in command units), all input-side effects applied.

    Args:
        u: command per sample (ZOH).
        period_s: sample period [s].
        hp: hyper-parameters present (delay_s, limit_u, width_u, halfwidth_u, tau_s).
        scale: optional per-sample multiplier applied before the lag (battery term).
    """
    w = np.asarray(u, dtype=float)
    delay_s = hp.get("delay_s", 0.0)
    if delay_s > 0:
        # Interval average of a ZOH signal delayed by (n + f) periods.
        q = delay_s / period_s
        n, f = int(math.floor(q)), q - math.floor(q)
        shifted = np.concatenate([np.full(n + 1, w[0]), w])[: w.shape[0] + 1]
        w = (1 - f) * shifted[1:] + f * shifted[:-1]
    limit = hp.get("limit_u", math.inf)
    if math.isfinite(limit):
        w = np.clip(w, -limit, limit)
    width = hp.get("width_u", 0.0)
    if width > 0:
        w = np.sign(w) * np.maximum(np.abs(w) - width, 0.0)
    hw = hp.get("halfwidth_u", 0.0)
    if hw > 0:
        w = backlash_play(w, hw)
    if scale is not None:
        w = w * scale
    tau_s = hp.get("tau_s", 0.0)
    if tau_s > 0:
        # Exact ZOH first-order lag y' = (w - y)/tau; return the interval average of y.
        alpha = math.exp(-period_s / tau_s)
        y0 = w[0]
        y, _ = lfilter([0.0, 1 - alpha], [1.0, -alpha], w, zi=[alpha * y0])
        y[0] = y0
        w = w + (y - w) * (tau_s / period_s) * (1 - alpha)
    return w


# ----------------------------------------------------------------------------- parameters


@dataclass
class AxisParams:
    """Everything needed to simulate: coefficients, effect hyper-parameters, sensor model."""

    effects: list[str]
    coef: dict[str, float]
    hyper: dict[str, float]
    sensor: dict[str, float] = field(default_factory=lambda: {"bias_v": 0.0, "scale_v": 1.0})
    eps_v: float = 1e-3  # velocity [x/s] below which friction's sign is smoothed in regressions
    vbat_ref_v: float = 1.0
    period_s: float = 0.01
    sg_window: int = 7
    k_u: float | None = None  # known actuator gain (force per command unit), if given
    #: hyper-parameters whose best value stayed at the edge of the search grid after widening it
    at_bound: dict[str, float] = field(default_factory=dict)

    def effect_params(self, name: str) -> dict[str, float]:
        """The parameters reported for one effect, in the catalogue's units."""
        if name == "cogging":
            k = self.hyper["cog_k"]
            return {"gc_acc": self.coef["gc_acc"], "k_rad_per_x": k, "period_x": 2 * math.pi / k,
                    "phase_rad": self.hyper["cog_phase"]}
        if name in ("stribeck_friction", "gravity_load"):
            return {COEF_OF[name]: self.coef[COEF_OF[name]], HYPER_OF[name]: self.hyper[HYPER_OF[name]]}
        if name in HYPER_OF:
            return {HYPER_OF[name]: self.hyper[HYPER_OF[name]]}
        if name == "battery_sag":
            return {"gain_per_rel_v": self.coef["kb"] / self.coef["a"], "vbat_ref_v": self.vbat_ref_v}
        if name == "asymmetric_friction":
            return {"fa_acc": self.coef["fa_acc"], "fc_acc": self.coef["fc_acc"]}
        if name in COEF_OF:
            return {COEF_OF[name]: self.coef[COEF_OF[name]]}
        if name == "sensor_bias":
            return {"bias_v": self.sensor["bias_v"]}
        if name == "sensor_scale":
            return {"scale_v": self.sensor["scale_v"]}
        raise KeyError(name)

    def primary(self, name: str) -> float:
        spec = CATALOGUE[name]
        return float(self.effect_params(name)[spec.primary])

    def primary_along(self, name: str, ref: AxisParams) -> float:
        """Primary of a position-periodic load measured along ``ref``'s phase [x/s²].

        A load −A·sin(k·x − φ) with φ in [−π/2, π/2) has two representations near φ = ±π/2 (A
        and −A, φ and φ ∓ π): a bootstrap replicate could flip the sign of A although the load is
        the same. Its projection on the reference load's phase, A·cos(φ − φ_ref), does not.
        """
        h = PHASE_OF.get(name)
        if h is None:
            return self.primary(name)
        return self.primary(name) * math.cos(self.hyper[h] - ref.hyper[h])

    def physical(self) -> dict[str, float] | None:
        """Physical parameters when k_u (force per command unit) is known."""
        if not self.k_u:
            return None
        j = self.k_u / self.coef["a"]
        out = {"k_u": self.k_u, "J": j, "b": self.coef["c_per_s"] * j}
        names = {"fc_acc": "Fc", "fs_extra_acc": "Fs_minus_Fc", "offset_acc": "offset_force", "gravity_acc": "gravity_force",
                 "fa_acc": "Fc_asymmetry", "gl_acc": "gravity_load_force", "gc_acc": "cogging_force"}
        for k, phys in names.items():
            if k in self.coef:
                out[phys] = self.coef[k] * j
        return out

    def to_dict(self) -> dict:
        return {
            "effects": list(self.effects),
            "coef": dict(self.coef),
            "hyper": {k: (None if not math.isfinite(v) else v) for k, v in self.hyper.items()},
            "sensor": dict(self.sensor),
            "eps_v": self.eps_v,
            "vbat_ref_v": self.vbat_ref_v,
            "period_s": self.period_s,
            "sg_window": self.sg_window,
            "k_u": self.k_u,
        }

    @classmethod
    def from_dict(cls, d: dict) -> AxisParams:
        hyper = {k: (math.inf if v is None else float(v)) for k, v in d["hyper"].items()}
        return cls(effects=list(d["effects"]), coef={k: float(v) for k, v in d["coef"].items()}, hyper=hyper,
                   sensor={k: float(v) for k, v in d["sensor"].items()}, eps_v=float(d["eps_v"]),
                   vbat_ref_v=float(d["vbat_ref_v"]), period_s=float(d["period_s"]),
                   sg_window=int(d["sg_window"]), k_u=d.get("k_u"))


# ----------------------------------------------------------------------------- features


def state_velocity(p: Prepared, sensor: dict[str, float]) -> np.ndarray:
    """True-units velocity from the observed channel through the inverse sensor model."""
    return (p.v_obs - sensor["bias_v"]) / sensor["scale_v"]


def _payload_factor(p: Prepared, hyper: dict[str, float]) -> np.ndarray | None:
    mu = hyper.get("mu_per_unit", 0.0)
    if mu == 0.0 or p.ep.payload is None:
        return None
    return 1.0 / np.maximum(1.0 + mu * p.ep.payload, 1e-3)


def _rel_vbat(p: Prepared, vbat_ref_v: float) -> np.ndarray:
    return (p.ep.vbat_v - vbat_ref_v) / vbat_ref_v


def coef_names(effects: list[str]) -> list[str]:
    names = list(NOMINAL_COEFS)
    for e in effects:
        if e in COEF_OF:
            names.append(COEF_OF[e])
    return names


#: The input chain's hyper-parameters with their no-effect values (what :func:`input_chain` reads).
_CHAIN_HYPERS = (("delay_s", 0.0), ("limit_u", math.inf), ("width_u", 0.0), ("halfwidth_u", 0.0), ("tau_s", 0.0))
#: Most cached feature columns per episode before the cache is emptied (bounds memory).
FEATURE_CACHE_MAX = 256


def _feature_cached(p: Prepared, key: tuple, make) -> np.ndarray:
    """A feature column of episode ``p`` from its cache, made (and kept) when missing. Columns are
    shared between calls: nobody writes into them."""
    col = p.feature_cache.get(key)
    if col is None:
        if len(p.feature_cache) >= FEATURE_CACHE_MAX:
            p.feature_cache.clear()
        col = p.feature_cache[key] = make()
    return col


def raw_features(p: Prepared, params: AxisParams, v: np.ndarray, smooth: bool) -> dict[str, np.ndarray]:
    """Per-sample features (acceleration per unit coefficient), length N.

    ``smooth`` applies the velocity estimator's kernel to the command-side features (for
    regression against an SG-derived velocity); simulation uses the raw features.
    """
    hp, eff = params.hyper, params.effects
    g = _payload_factor(p, hp)
    one = np.ones(p.n) if g is None else g
    sm = (lambda a: _smooth(p, a)) if smooth else (lambda a: a)
    feats: dict[str, np.ndarray] = {}
    # The command chain and its smoothed drive column depend on the input-side hyper-parameters only;
    # a coordinate search varies one hyper-parameter at a time, so they are cached per episode.
    chain_key = tuple(float(hp.get(h, d)) for h, d in _CHAIN_HYPERS)
    mu = float(hp.get("mu_per_unit", 0.0))
    fu = _feature_cached(p, ("chain", chain_key), lambda: input_chain(p.ep.u, p.period_s, hp))
    feats["a"] = _feature_cached(p, ("a", chain_key, mu, smooth), lambda: sm(fu * one))
    if "battery_sag" in eff:
        pre_lag = {k: v for k, v in hp.items() if k != "tau_s"}
        w = input_chain(p.ep.u, p.period_s, pre_lag) * _rel_vbat(p, params.vbat_ref_v)
        fb = input_chain(w, p.period_s, {"tau_s": hp.get("tau_s", 0.0)})
        feats["kb"] = sm(fb * one)
    if "back_emf" in eff:
        # (a − kemf·v)·u: the drive falls with speed while driven (back-EMF under PWM)
        feats["kemf"] = sm(-fu * one * v)
    feats["c_per_s"] = -v * one
    sgn = np.tanh(v / params.eps_v)
    if "coulomb_friction" in eff:
        feats["fc_acc"] = -sgn * one
    if "stribeck_friction" in eff:
        feats["fs_extra_acc"] = -np.exp(-((v / hp["vs"]) ** 2)) * sgn * one
    if "force_offset" in eff:
        feats["offset_acc"] = _feature_cached(p, ("offset", mu, smooth), lambda: sm(one.copy()))
    if "slope" in eff:
        feats["gravity_acc"] = np.ones(p.n)
    if "asymmetric_friction" in eff:
        # Direction-dependent part of Coulomb friction: Fc+ = fc + fa forward, Fc- = fc - fa backward.
        feats["fa_acc"] = -np.abs(sgn) * one
    if "gravity_load" in eff:
        # Position-dependent load, e.g. gravity on a rotary joint: x in rad, q0 the hanging angle.
        feats["gl_acc"] = -np.sin(p.ep.x - hp["q0_rad"]) * one
    if "cogging" in eff:
        # Position-periodic load (cogging, detent): k = n per revolution when x is in rad.
        feats["gc_acc"] = -np.sin(hp["cog_k"] * p.ep.x - hp["cog_phase"]) * one
    return feats


def design(p: Prepared, params: AxisParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Regression design on the valid samples: (X [n, p], y [n] in x/s², index k of each row)."""
    v = state_velocity(p, params.sensor)
    feats = raw_features(p, params, v, smooth=True)
    names = coef_names(params.effects)
    k = np.arange(p.margin, p.n - p.margin - 1)
    k = k[p.moving[k]]
    X = np.stack([feats[nm][k] for nm in names], axis=1)
    y = (v[k + 1] - v[k]) / p.period_s
    return X, y, k


@dataclass
class Stats:
    """Sufficient statistics of one episode's regression: X'X, X'y, y'y, n."""

    xtx: np.ndarray
    xty: np.ndarray
    yty: float
    n: int


#: Most configurations cached per episode before the cache is emptied (bounds memory).
STATS_CACHE_MAX = 4096


def _stats_key(params: AxisParams) -> tuple:
    """Everything :func:`design` reads from ``params`` (the episode's own data is fixed)."""
    return (tuple(params.effects), tuple(sorted(params.hyper.items())), params.sensor["bias_v"],
            params.sensor["scale_v"], params.eps_v, params.vbat_ref_v)


def episode_stats(preps: list[Prepared], params: AxisParams, weights: np.ndarray | None = None) -> list[Stats | None]:
    """Per-episode regression statistics, cached on each episode.

    The selection fits the same episode with the same effects and hyper-parameter values many
    times (every fold that trains on it, every bootstrap replicate, the same grid point in every
    round); the statistics depend only on the episode and :func:`_stats_key`, so they are
    computed once. Weights (folds, bootstrap counts) are applied later in :func:`solve`; an episode
    of weight 0 (held out, not drawn) gets None instead of statistics nobody reads.
    """
    key = _stats_key(params)
    out: list[Stats | None] = []
    for i, p in enumerate(preps):
        if weights is not None and not weights[i]:
            out.append(None)
            continue
        s = p.stats_cache.get(key)
        if s is None:
            X, y, _ = design(p, params)
            s = Stats(X.T @ X, X.T @ y, float(y @ y), int(y.shape[0]))
            if len(p.stats_cache) >= STATS_CACHE_MAX:
                p.stats_cache.clear()
            p.stats_cache[key] = s
        out.append(s)
    return out


def solve(stats: list[Stats], weights: np.ndarray | None = None) -> tuple[np.ndarray, float, int]:
    """Weighted least squares from per-episode statistics: (theta, SSE, n)."""
    w = np.ones(len(stats)) if weights is None else weights
    xtx = sum(wi * s.xtx for wi, s in zip(w, stats, strict=True) if wi)
    xty = sum(wi * s.xty for wi, s in zip(w, stats, strict=True) if wi)
    yty = sum(wi * s.yty for wi, s in zip(w, stats, strict=True) if wi)
    n = int(sum(wi * s.n for wi, s in zip(w, stats, strict=True) if wi))
    ridge = 1e-10 * (np.trace(xtx) / xtx.shape[0] + 1e-30)
    theta = np.linalg.solve(xtx + ridge * np.eye(xtx.shape[0]), xty)
    sse = float(yty - 2 * theta @ xty + theta @ xtx @ theta)
    return theta, max(sse, 0.0), n


def sse_of(stats: list[Stats], theta: np.ndarray, idx) -> float:
    return float(sum(stats[i].yty - 2 * theta @ stats[i].xty + theta @ stats[i].xtx @ theta for i in idx))


# ----------------------------------------------------------------------------- grids


def hyper_grid(name: str, preps: list[Prepared], widen: int = 0) -> np.ndarray:
    """Search grid of one hyper-parameter, scaled to the data.

    ``widen`` = 1, 2, ...: the grid after its best point was found at the far edge that many
    times; it reaches further (twice as far each time, within what the data can mean: a
    deadband or a backlash no wider than the largest command).
    """
    dt = preps[0].period_s
    au = np.abs(np.concatenate([p.ep.u for p in preps]))
    f = 2.0**widen
    if name == "delay_s":
        mx = max_delay_samples(dt) * f
        steps = np.unique(np.concatenate([np.arange(0, 4.01, 0.5), np.geomspace(5, mx, 10 + 4 * widen).round()]))
        return steps[steps <= mx] * dt
    if name == "tau_s":
        return np.concatenate([[0.0], np.geomspace(0.3 * dt, f * max(0.3, 30 * dt), 18 + 4 * widen)])
    if name == "width_u":
        return np.linspace(0, min(f * np.quantile(au, 0.6), np.max(au)), 21)
    if name == "halfwidth_u":
        return np.linspace(0, min(f * 0.5 * np.quantile(au, 0.9), np.max(au)), 21)
    if name == "halfwidth_x":
        # Play up to 5 % of the typical stroke (log-spaced: a play is small against the stroke).
        span = float(np.median([np.ptp(p.ep.x) for p in preps])) or 1.0
        hi = f * 0.05 * span
        return np.concatenate([[0.0], np.geomspace(hi / 200, hi, 20)])
    if name == "limit_u":
        return np.concatenate([np.quantile(au, np.linspace(0.4 / f, 0.995, 20 + 4 * widen)), [math.inf]])
    if name == "vs":
        vr = float(np.sqrt(np.mean(np.concatenate([p.v_obs for p in preps]) ** 2)))
        return np.geomspace(0.01 / f, f, 14 + 4 * widen) * vr
    if name == "mu_per_unit":
        pm = np.concatenate([p.ep.payload for p in preps])
        span = float(np.max(np.abs(pm))) or 1.0
        return np.linspace(-0.5, 3.0 * f, 36) / span
    if name == "cog_k":
        return cogging_grid(preps)
    if name == "q0_rad":
        return np.linspace(-math.pi / 2, math.pi / 2, 24, endpoint=False)  # q0 and q0 + pi: same load, sign flipped
    raise KeyError(name)


#: Hyper-parameters whose grid is widened when the best value sits at its far edge, and which edge.
#: (q0 is periodic; a delay, lag, width or Stribeck speed at the top, a saturation at the bottom.)
WIDEN_EDGE = {"delay_s": -1, "tau_s": -1, "width_u": -1, "halfwidth_u": -1, "vs": -1, "mu_per_unit": -1,
              "limit_u": 0, "halfwidth_x": -1}
MAX_WIDEN = 2


def _at_edge(h: str, i: int, grid: np.ndarray) -> bool:
    edge = WIDEN_EDGE.get(h)
    return edge is not None and i == (len(grid) - 1 if edge == -1 else 0) and math.isfinite(grid[i])


# ----------------------------------------------------------------------------- fitting


def initial_params(preps: list[Prepared], effects: list[str], k_u: float | None = None) -> AxisParams:
    v = np.concatenate([p.v_obs for p in preps])
    vbat = [p.ep.vbat_v for p in preps if p.ep.vbat_v is not None]
    hyper = {}
    for e in effects:
        if e in HYPER_OF:
            h = HYPER_OF[e]
            hyper[h] = {"vs": 0.1 * float(np.sqrt(np.mean(v**2)))}.get(h, HYPER_NO_EFFECT[h])
    if "cogging" in effects:
        hyper["cog_phase"] = HYPER_NO_EFFECT["cog_phase"]
    window = preps[0].window
    return AxisParams(
        effects=list(effects),
        coef={},
        hyper=hyper,
        # Friction's sign is smoothed only below the stop threshold (rows there are masked anyway).
        eps_v=max(1e-9, 0.3 * float(np.median([p.v_min for p in preps]))),
        vbat_ref_v=float(np.mean(np.concatenate(vbat))) if vbat else 1.0,
        period_s=preps[0].period_s,
        sg_window=window,
        k_u=k_u,
    )


def fit_sensor(preps: list[Prepared], effects: list[str], weights: np.ndarray | None = None) -> dict[str, float]:
    """Velocity sensor bias/scale against the SG derivative of position (same kernel both sides)."""
    if not any(e in effects for e in SENSOR_EFFECTS):
        return {"bias_v": 0.0, "scale_v": 1.0}
    kernel = sg_velocity_kernel(preps[0].window)
    ws = np.ones(len(preps)) if weights is None else weights
    rows_x, rows_y, rows_w = [], [], []
    for wi, p in zip(ws, preps, strict=True):
        if not wi:
            continue
        m = len(kernel) // 2
        vm = np.convolve(np.concatenate([np.full(m, p.v_obs[0]), p.v_obs, np.full(m, p.v_obs[-1])]), kernel, "valid")
        k = slice(p.margin, p.n - p.margin)
        rows_x.append(p.v_from_x[k])
        rows_y.append(vm[k])
        rows_w.append(np.full(rows_x[-1].shape, wi))
    vx, vm, w = np.concatenate(rows_x), np.concatenate(rows_y), np.concatenate(rows_w)
    fit_bias, fit_scale = "sensor_bias" in effects, "sensor_scale" in effects
    if fit_bias and fit_scale:
        A = np.stack([vx, np.ones_like(vx)], 1)
        s, b = np.linalg.lstsq(A * w[:, None] ** 0.5, vm * w**0.5, rcond=None)[0]
    elif fit_scale:
        s, b = float(np.sum(w * vx * vm) / np.sum(w * vx * vx)), 0.0
    else:
        s, b = 1.0, float(np.sum(w * (vm - vx)) / np.sum(w))
    return {"bias_v": float(b), "scale_v": float(s)}


def _parabola_min(x, y) -> float:
    """Vertex of the parabola through three points (grid refinement without extra fits)."""
    x0, x1, x2 = map(float, x)
    y0, y1, y2 = map(float, y)
    den = (x0 - x1) * (x0 - x2) * (x1 - x2)
    if den == 0:
        return x1
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
    b = (x2**2 * (y0 - y1) + x1**2 * (y2 - y0) + x0**2 * (y1 - y2)) / den
    if a <= 0:
        return x1
    return float(min(max(-b / (2 * a), x0), x2))


def _sse_for(preps, params, weights):
    stats = episode_stats(preps, params, weights)
    theta, sse, _ = solve(stats, weights)
    return sse, theta


def fit_axis(preps: list[Prepared], effects: list[str], weights: np.ndarray | None = None,
             refine: bool = True, k_u: float | None = None, start: AxisParams | None = None,
             passes: int = 2, search: list[str] | None = None) -> AxisParams:
    """Grey-box fit of the axis model with the given effects on (weighted) episodes.

    Hyper-parameters by coordinate search (grid, then bounded refinement); a and c and all
    linear effect coefficients by least squares inside every evaluation. ``search`` limits the
    search to the hyper-parameters of these effects (the others keep their ``start`` values).
    """
    effects = [e for e in effects if CATALOGUE[e].absorbed_by_nominal == ""]
    params = initial_params(preps, effects, k_u)
    if start is not None:
        for h in params.hyper:
            if h in start.hyper:
                params.hyper[h] = start.hyper[h]
    params.sensor = fit_sensor(preps, effects, weights)
    hyper_names = [h for h in params.hyper if h != "cog_phase"]  # the phase comes with cog_k
    if search is not None:
        hyper_names = [HYPER_OF[e] for e in search if e in HYPER_OF and HYPER_OF[e] in params.hyper]
    output_names = [h for h in hyper_names if h in OUTPUT_HYPERS]
    hyper_names = [h for h in hyper_names if h not in OUTPUT_HYPERS]
    for _ in range(passes if len(hyper_names) > 1 else 1):
        for h in hyper_names:
            if h == "cog_k":
                _fit_cogging(preps, params, weights)
                continue
            for widen in range(MAX_WIDEN + 1):
                grid = hyper_grid(h, preps, widen)
                sses = []
                for val in grid:
                    params.hyper[h] = float(val)
                    sses.append(_sse_for(preps, params, weights)[0])
                i = int(np.argmin(sses))
                if not _at_edge(h, i, grid) or grid[i] == hyper_grid(h, preps, widen + 1)[
                        -1 if WIDEN_EDGE[h] == -1 else 0]:
                    break
            params.hyper[h] = float(grid[i])
            if _at_edge(h, i, grid):
                params.at_bound[h] = float(grid[i])
            else:
                params.at_bound.pop(h, None)
            if not refine and 0 < i < len(grid) - 1 and math.isfinite(grid[i + 1]):
                params.hyper[h] = _parabola_min(grid[i - 1 : i + 2], sses[i - 1 : i + 2])
            if refine and math.isfinite(grid[i]):
                lo = grid[max(i - 1, 0)]
                hi = grid[min(i + 1, len(grid) - 1)]
                if not math.isfinite(hi):
                    hi = grid[i] * 1.5
                if hi > lo:
                    from scipy.optimize import minimize_scalar

                    def f(val, h=h):
                        params.hyper[h] = float(val)
                        return _sse_for(preps, params, weights)[0]

                    r = minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": (hi - lo) * 1e-3})
                    params.hyper[h] = float(r.x) if r.fun <= sses[i] else float(grid[i])
    _, theta = _sse_for(preps, params, weights)
    params.coef = dict(zip(coef_names(effects), map(float, theta), strict=True))
    for h in output_names:
        _fit_output_hyper(preps, params, h, weights)
    if OUTPUT_ERROR_REFINE:
        refine_output_error(preps, params, weights)
    return params


#: Spatial-frequency grid of the cogging search: at least two periods over the typical stroke, at
#: least ``COG_MIN_TRAVEL_SAMPLES`` samples of travel at the rms speed per period, steps of a
#: quarter of the frequency resolution 2π/stroke, at most ``COG_MAX_GRID`` values.
COG_MIN_TRAVEL_SAMPLES = 8
COG_MAX_GRID = 400


def cogging_grid(preps: list[Prepared]) -> np.ndarray:
    """Spatial frequencies k [rad per x-unit] searched for a position-periodic load (may be empty)."""
    span = float(np.median([np.ptp(p.ep.x) for p in preps]))
    v_rms = float(np.sqrt(np.mean(np.concatenate([p.v_obs for p in preps]) ** 2)))
    if span <= 0 or v_rms <= 0:
        return np.empty(0)
    k_lo = 2 * 2 * math.pi / span
    k_hi = 2 * math.pi / (COG_MIN_TRAVEL_SAMPLES * v_rms * preps[0].period_s)
    if k_hi <= k_lo:
        return np.empty(0)
    step = max(0.25 * 2 * math.pi / span, (k_hi - k_lo) / COG_MAX_GRID)
    return np.arange(k_lo, k_hi + 0.5 * step, step)


def _cogging_profile(preps: list[Prepared], params: AxisParams, ks: np.ndarray,
                     weights: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares SSE of the model + a load βs·sin(k·x) + βc·cos(k·x), for every k at once.

    The load is linear in (βs, βc) for a fixed k, so the profile over k is a bordered normal
    equation per k (a periodogram of the residual, adjusted for the model's other terms).
    Returns (SSE per k, (βs, βc) per k).
    """
    base = AxisParams(**{**params.__dict__, "effects": [e for e in params.effects if e != "cogging"],
                         "at_bound": {}})
    ws = np.ones(len(preps)) if weights is None else weights
    G = len(ks)
    q = len(coef_names(base.effects))
    A = np.zeros((G, q + 2, q + 2))
    b = np.zeros((G, q + 2))
    yty = 0.0
    for wi, p in zip(ws, preps, strict=True):
        if not wi:
            continue
        X, y, k = design(p, base)
        g = _payload_factor(p, params.hyper)
        one = np.ones(k.size) if g is None else g[k]
        phase = p.ep.x[k][:, None] * ks[None, :]
        S, C = -np.sin(phase) * one[:, None], -np.cos(phase) * one[:, None]
        A[:, :q, :q] += wi * (X.T @ X)
        A[:, :q, q] += wi * (X.T @ S).T
        A[:, :q, q + 1] += wi * (X.T @ C).T
        A[:, q, q] += wi * np.einsum("ng,ng->g", S, S)
        A[:, q, q + 1] += wi * np.einsum("ng,ng->g", S, C)
        A[:, q + 1, q + 1] += wi * np.einsum("ng,ng->g", C, C)
        b[:, :q] += wi * (X.T @ y)[None, :]
        b[:, q] += wi * (S.T @ y)
        b[:, q + 1] += wi * (C.T @ y)
        yty += wi * float(y @ y)
    A[:, q:, :q] = np.transpose(A[:, :q, q:], (0, 2, 1))
    A[:, q + 1, q] = A[:, q, q + 1]
    ridge = 1e-10 * (np.trace(A, axis1=1, axis2=2) / (q + 2))[:, None, None] * np.eye(q + 2)[None]
    theta = np.linalg.solve(A + ridge, b[..., None])[..., 0]
    sse = yty - np.einsum("gi,gi->g", theta, b)
    return sse, theta[:, q:]


def _fit_cogging(preps: list[Prepared], params: AxisParams, weights: np.ndarray | None) -> None:
    """Spatial frequency k by the profile over :func:`cogging_grid` (refined on a finer grid
    around the best value); phase φ in [−π/2, π/2) and the signed amplitude from (βs, βc)."""
    grid = cogging_grid(preps)
    if grid.size == 0:
        params.hyper["cog_k"], params.hyper["cog_phase"] = HYPER_NO_EFFECT["cog_k"], 0.0
        return
    sse, beta = _cogging_profile(preps, params, grid, weights)
    i = int(np.argmin(sse))
    if i in (0, grid.size - 1):
        params.at_bound["cog_k"] = float(grid[i])
    else:
        params.at_bound.pop("cog_k", None)
    fine = np.linspace(grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)], 17)
    fsse, fbeta = _cogging_profile(preps, params, fine, weights)
    j = int(np.argmin(fsse))
    k, (bs, bc) = (float(fine[j]), fbeta[j]) if fsse[j] <= sse[i] else (float(grid[i]), beta[i])
    # βs·(−sin kx) + βc·(−cos kx) = −A·sin(kx − φ) with A·cos φ = βs and −A·sin φ = βc.
    amp, phi = math.hypot(bs, bc), math.atan2(-bc, bs)
    if phi >= math.pi / 2:
        phi -= math.pi
    elif phi < -math.pi / 2:
        phi += math.pi
    params.hyper["cog_k"], params.hyper["cog_phase"] = k, phi
    del amp  # the signed amplitude comes out of the final least squares with this phase


def _window_sse_grid(preps: list[Prepared], params: AxisParams, h: str, grid: np.ndarray,
                     weights: np.ndarray | None) -> np.ndarray:
    """Weighted open-loop position SSE over all episodes for each value of output hyper ``h``.

    All grid values are replayed at once (windows × grid values in one vectorised replay).
    """
    ws = np.ones(len(preps)) if weights is None else weights
    horizon = max(2, int(round(OUTPUT_FIT_HORIZON_S / preps[0].period_s)))
    total = np.zeros(len(grid))
    jobs, used = [], []
    for wi, p in zip(ws, preps, strict=True):
        if not wi:
            continue
        hz = max(1, min(horizon, p.n - 2 * p.margin - 2))
        starts = window_starts(p, hz)
        jobs.append((p, params, np.tile(starts, len(grid)), np.repeat(np.asarray(grid, float), starts.size)))
        used.append((wi, starts.size))
    for (wi, n_starts), sim in zip(used, simulate_many(jobs, horizon), strict=True):
        err = np.sum((sim["x_pred"] - sim["x_true"]) ** 2, axis=1).reshape(len(grid), n_starts)
        total += wi * err.sum(axis=1)
    return total


def _fit_output_hyper(preps: list[Prepared], params: AxisParams, h: str, weights: np.ndarray | None) -> None:
    """Fit an output-side hyper-parameter by open-loop position error (grid, widened, then a finer grid)."""
    for widen in range(MAX_WIDEN + 1):
        grid = hyper_grid(h, preps, widen)
        sses = _window_sse_grid(preps, params, h, grid, weights)
        i = int(np.argmin(sses))
        if not _at_edge(h, i, grid):
            break
    if _at_edge(h, i, grid):
        params.at_bound[h] = float(grid[i])
    else:
        params.at_bound.pop(h, None)
    fine = np.linspace(grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)], 11)
    fine_sses = _window_sse_grid(preps, params, h, fine, weights)
    j = int(np.argmin(fine_sses))
    params.hyper[h] = float(fine[j]) if fine_sses[j] <= sses[i] else float(grid[i])


# ----------------------------------------------------------------------------- output-error refinement

#: Refine the linear coefficients by output error after the equation-error fit (see
#: :func:`refine_output_error`). False: equation error only (the behaviour before issue 28's round 5).
OUTPUT_ERROR_REFINE = True
#: Open-loop windows of the output-error fit: horizon [s] (at most ``OE_MAX_STEPS`` samples), at
#: most ``OE_MAX_WINDOWS`` windows spread evenly over the weighted episodes, and the solver budget.
OE_HORIZON_S = 1.0
OE_MAX_STEPS = 200
OE_MAX_WINDOWS = 64
OE_MAX_NFEV = 8


def _oe_jobs(preps: list[Prepared], params: AxisParams, weights: np.ndarray | None) -> tuple[list[dict], np.ndarray]:
    """Replay jobs (features built once) on a subset of open-loop windows, and each job's weight."""
    ws = np.ones(len(preps)) if weights is None else np.asarray(weights, float)
    horizon = max(2, min(int(round(OE_HORIZON_S / preps[0].period_s)), OE_MAX_STEPS))
    # One horizon for every window (they are replayed stacked): an episode too short to hold it
    # is left out of the refinement (it still counts in the equation-error fit); when none holds
    # it, the horizon is the longest any weighted episode holds.
    usable = {i: p.n - 2 * p.margin - 2 for i, (wi, p) in enumerate(zip(ws, preps, strict=True)) if wi > 0}
    if not usable:
        return [], np.zeros(0)
    horizon = min(horizon, max(max(usable.values()), 1))
    starts = {}
    for i, n_use in usable.items():
        if n_use >= horizon:
            starts[i] = window_starts(preps[i], horizon)
    total = sum(s.size for s in starts.values())
    stride = max(1, math.ceil(total / OE_MAX_WINDOWS))
    jobs, wts, seen = [], [], 0
    for i, st in starts.items():
        pick = st[(np.arange(st.size) + seen) % stride == 0]  # every stride-th window across episodes
        seen += st.size
        if pick.size:
            jobs.append(_replay_job(preps[i], params, horizon, pick, None))
            wts.append(ws[i])
    return jobs, np.asarray(wts, float)


def refine_output_error(preps: list[Prepared], params: AxisParams, weights: np.ndarray | None = None) -> bool:
    """Refine the linear coefficients (a, c and every effect's) by output error, in place.

    Equation error regresses (v_{k+1} − v_k)/Δt on features of the measured v_k. When v is a
    noisy estimate (the Savitzky-Golay derivative of a coarsely quantised position: 1 cm
    odometry), the same noise sits in the regressor −c·v_k and, with the opposite sign, in the
    target, which biases c (and a with it) upwards: an errors-in-variables bias. Output error
    simulates the model open loop over windows of the recording (``OE_HORIZON_S`` from each
    window's measured state, the logged commands replayed) and minimises the position and
    velocity errors of the simulation, whose noise is in the output only, so it has no such bias
    (Ljung, *System Identification*, 2nd ed., §7.3 and §8.3: output-error models are consistent
    under white measurement noise where equation error is not). Started from the equation-error
    fit; scipy's ``least_squares`` (trust region) with a finite-difference Jacobian whose columns
    are replayed in one vectorised batch. Each channel is scaled by its error at the start, a
    Gaussian likelihood with one noise variance per channel, as the selection scores channels.
    The hyper-parameters (delay, lag, widths) stay at their equation-error values. The result is
    kept only when it lowers the error and is finite. Returns whether the coefficients changed.
    """
    from scipy.optimize import least_squares

    names = coef_names(params.effects)
    theta0 = np.array([params.coef[n] for n in names], float)
    jobs, wts = _oe_jobs(preps, params, weights)
    if not jobs or not np.all(np.isfinite(theta0)):
        return False
    # The windows of all jobs stacked once; each evaluation replays them for every parameter vector
    # asked for (the Jacobian's columns together) with only the coefficient matrix rebuilt.
    base = _stack(jobs)
    n_w = base["idx"].size
    sw = np.concatenate([np.full(j["starts"].size, np.sqrt(wi)) for j, wi in zip(jobs, wts, strict=True)])[:, None]
    horizon, dt = jobs[0]["horizon"], jobs[0]["p"].period_s
    ks = [j["starts"][:, None] + 1 + np.arange(horizon)[None, :] for j in jobs]
    x_true = np.concatenate([j["p"].ep.x[k] for j, k in zip(jobs, ks, strict=True)])
    v_true = np.concatenate([j["p"].v_obs[k] for j, k in zip(jobs, ks, strict=True)])
    s_v, b_v = params.sensor["scale_v"], params.sensor["bias_v"]
    col = [COEF_COLUMNS.index(n) for n in names]
    fixed = base["coef"][0].copy()  # coefficients outside ``names`` (none: all linear ones are refined)

    tiled: dict[int, dict[str, np.ndarray]] = {}  # the windows repeated for m parameter vectors

    def errors(thetas: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        m = len(thetas)
        if m not in tiled:
            tiled[m] = {k: (vv if k in ("u_in", "kb_in", "g") else np.tile(vv, m)) for k, vv in base.items()
                        if k != "coef"}
        st = dict(tiled[m])
        coef = np.tile(fixed, (m, 1))
        coef[:, col] = np.asarray(thetas, float)
        st["coef"] = np.repeat(coef, n_w, axis=0)
        with np.errstate(all="ignore"):
            xs, vs_out = _replay_stacked(st, horizon, dt)
            out = []
            for t in range(m):
                sl = slice(t * n_w, (t + 1) * n_w)
                out.append(((sw * (xs[sl] - x_true)).ravel(), (sw * ((s_v * vs_out[sl] + b_v) - v_true)).ravel()))
        return out

    ex0, ev0 = errors([theta0])[0]
    sx = float(np.sqrt(np.mean(ex0**2))) or 1.0
    sv = float(np.sqrt(np.mean(ev0**2))) or 1.0
    big = 1e6

    def resid(pair):
        r = np.concatenate([pair[0] / sx, pair[1] / sv])
        return np.where(np.isfinite(r), np.clip(r, -big, big), big)

    cache: dict[bytes, np.ndarray] = {}

    def fun(th):
        r = resid(errors([th])[0])
        cache.clear()
        cache[th.tobytes()] = r
        return r

    scale = np.maximum(np.abs(theta0), 1e-3 * (np.max(np.abs(theta0)) + 1e-12))
    steps = 1e-4 * scale

    def jac(th):
        r0 = cache.get(th.tobytes())
        if r0 is None:
            r0 = fun(th)
        pert = [th + steps[j] * np.eye(th.size)[j] for j in range(th.size)]
        cols = [(resid(e) - r0) / steps[j] for j, e in enumerate(errors(pert))]
        return np.stack(cols, axis=1)

    r_start = resid((ex0, ev0))
    cost0 = float(r_start @ r_start)
    try:
        sol = least_squares(fun, theta0, jac=jac, method="trf", x_scale="jac", max_nfev=OE_MAX_NFEV,
                            ftol=1e-4, xtol=1e-4)
    except (ValueError, np.linalg.LinAlgError):
        return False
    if not np.all(np.isfinite(sol.x)) or 2 * sol.cost >= cost0:
        return False
    params.coef = dict(zip(names, map(float, sol.x), strict=True))
    return True


# ----------------------------------------------------------------------------- prediction


@dataclass
class Scores:
    """Squared errors of one episode: one-step and multi-step, per channel (x, v)."""

    one_sse: dict[str, float]
    one_n: int
    multi_sse: dict[str, float]
    multi_n: int


def predict_one_step(p: Prepared, params: AxisParams) -> dict[str, np.ndarray]:
    """One-step predictions of the observed channels at k+1 from measured state at k."""
    X, _, k = design(p, params)
    theta = np.array([params.coef[n] for n in coef_names(params.effects)])
    v = state_velocity(p, params.sensor)
    v_next = v[k] + p.period_s * (X @ theta)
    x_next = p.ep.x[k] + p.period_s * 0.5 * (v[k] + v_next)
    s, b = params.sensor["scale_v"], params.sensor["bias_v"]
    return {
        "k": k,
        "x_pred": x_next,
        "x_true": p.ep.x[k + 1],
        "x_prev": p.ep.x[k],
        "v_pred": s * v_next + b,
        "v_true": p.v_obs[k + 1],
        "v_prev": p.v_obs[k],
    }


def window_starts(p: Prepared, horizon: int) -> np.ndarray:
    last = p.n - p.margin - horizon - 1
    if last < p.margin:
        return np.array([p.margin], dtype=int)
    stride = max(1, horizon // 2)
    return np.arange(p.margin, last + 1, stride, dtype=int)


def motion_direction(v: np.ndarray, v_min: float) -> np.ndarray:
    """Sign of the last velocity above ``v_min`` at or before each sample (+1 before any motion)."""
    moving = np.abs(v) > v_min
    last = np.maximum.accumulate(np.where(moving, np.arange(v.size), -1))
    return np.where(last >= 0, np.sign(v[np.maximum(last, 0)]), 1.0)


def simulate_windows(p: Prepared, params: AxisParams, horizon: int,
                     starts: np.ndarray | None = None, play: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Open-loop simulation of H-step windows, replaying the logged commands.

    Each window starts from the measured position and velocity at its start index.
    Returns x/v predictions and measurements, shape (windows, H).

    With load-side play (``halfwidth_x``, or ``play`` [x-units] per window) the measured
    position is the load's: the motor starts at load + h·(direction of the last motion), moves
    by the model, and the load follows only while pushed at one end of the gap (its velocity is
    the motor's then, zero in the gap).
    """
    return simulate_many([(p, params, starts, play)], horizon)[0]


def _replay_job(p: Prepared, params: AxisParams, horizon: int, starts, play) -> dict:
    """Everything one (episode, parameters) replay needs: series over the episode, values per window."""
    horizon = max(1, min(horizon, p.n - 2 * p.margin - 2))
    if starts is None:
        starts = window_starts(p, horizon)
    starts = np.asarray(starts, dtype=int)
    v_true = state_velocity(p, params.sensor)
    feats = raw_features(p, params, v_true, smooth=False)  # only command-side columns used below
    hp = params.hyper
    g = _payload_factor(p, hp)
    g = np.ones(p.n) if g is None else g
    w = starts.size
    if play is None and hp.get("halfwidth_x", 0.0) > 0:
        play = np.full(w, hp["halfwidth_x"])
    x0 = p.ep.x[starts].astype(float)
    has_play = play is not None
    play_w = np.zeros(w) if play is None else np.broadcast_to(np.asarray(play, float), (w,))
    motor0 = x0 + play_w * motion_direction(v_true, p.v_min)[starts] if has_play else x0.copy()
    kb_in = feats.get("kb")
    job = {"p": p, "params": params, "horizon": horizon, "starts": starts, "g": g,
           "u_in": feats["a"], "kb_in": np.zeros(p.n) if kb_in is None else kb_in,
           "x_load": x0, "x": motor0, "v": v_true[starts].astype(float).copy(),
           "has_play": np.full(w, has_play), "play": play_w,
           "vs": np.full(w, float(hp.get("vs", 1.0))), "q0": np.full(w, float(hp.get("q0_rad", 0.0))),
           "cog_k": np.full(w, float(hp.get("cog_k", 1.0))), "cog_phase": np.full(w, float(hp.get("cog_phase", 0.0)))}
    return _with_coef(job, params.coef)


def _coef_vector(c: dict[str, float]) -> np.ndarray:
    """The coefficients a replay reads, in :data:`compiled.COEF_COLUMNS` order (0 when absent)."""
    return np.array([float(c.get(k, 0.0)) for k in COEF_COLUMNS])


def _with_coef(job: dict, c: dict[str, float]) -> dict:
    """A replay job with the linear coefficients ``c`` (the features, which depend only on the
    hyper-parameters, are shared with ``job``). The drive of step k is
    a·u_k + kb·kb_k + offset·g_k + gravity_acc: command-side terms were multiplied by the payload
    factor g in raw_features; the offset gets g here, friction and loads in the replay."""
    return {**job, "coef": _coef_vector(c)}


#: How many replay jobs :func:`simulate_many` stacks into one vectorised replay (None: all of them).
#: 1 replays one episode at a time, as before the batching: `hil bench calibrate --speed` runs that
#: as the peer of the batched replay in the same process.
REPLAY_BATCH_JOBS: int | None = None
#: Run the numba-compiled replay (:mod:`calibration.compiled`) when numba is installed; False: the
#: numpy replay (`hil bench calibrate --speed` measures one against the other).
USE_COMPILED = True


def simulate_many(jobs, horizon: int) -> list[dict[str, np.ndarray]]:
    """:func:`simulate_windows` for many (episode, params, starts, play) jobs in one vectorised replay.

    The replay loop runs once per step of the horizon for all windows of all jobs (jobs with the
    same sample period and horizon are stacked; each window carries its own coefficients), so the
    per-step Python overhead is paid once instead of once per episode and per parameter set. Each
    window's arithmetic is that of the single-episode replay, so the results are the same.
    """
    built = [_replay_job(p, params, horizon, starts, play) for p, params, starts, play in jobs]
    return _replay_built(built)


def _replay_built(built: list[dict]) -> list[dict[str, np.ndarray]]:
    out: list[dict | None] = [None] * len(built)
    groups: dict[tuple, list[int]] = {}
    for i, b in enumerate(built):
        groups.setdefault((b["horizon"], b["p"].period_s), []).append(i)
    step = REPLAY_BATCH_JOBS or len(built) or 1
    for (hz, dt), members in groups.items():
        for lo in range(0, len(members), step):
            chunk = members[lo: lo + step]
            for i, res in zip(chunk, _replay_group([built[i] for i in chunk], hz, dt), strict=True):
                out[i] = res
    return out


_WINDOW_KEYS = ("x", "v", "x_load", "has_play", "play", "vs", "q0", "cog_k", "cog_phase")


def _stack(built: list[dict]) -> dict[str, np.ndarray]:
    """The jobs' series end to end and their windows' values stacked (a window indexes the series
    through its job's offset)."""
    offsets = np.cumsum([0] + [b["g"].size for b in built[:-1]])
    st = {k: np.concatenate([b[k] for b in built]) for k in ("u_in", "kb_in", "g") + _WINDOW_KEYS}
    st["idx"] = np.concatenate([b["starts"] + o for b, o in zip(built, offsets, strict=True)])
    st["coef"] = np.concatenate([np.broadcast_to(b["coef"], (b["starts"].size, len(COEF_COLUMNS)))
                                 for b in built])
    return st


def _replay_stacked(st: dict[str, np.ndarray], horizon: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Open-loop positions and velocities [windows, horizon] of stacked windows (compiled or numpy)."""
    n_w = st["idx"].size
    xs, vs_out = np.empty((n_w, horizon)), np.empty((n_w, horizon))
    run = compiled.replay if USE_COMPILED else None
    if run is None:
        run = _replay_numpy
    run(float(dt), int(horizon), st["idx"], st["x"], st["v"], st["x_load"], st["has_play"], st["play"], st["vs"],
        st["q0"], st["cog_k"], st["cog_phase"], np.ascontiguousarray(st["coef"]), st["u_in"], st["kb_in"], st["g"],
        xs, vs_out)
    return xs, vs_out


def _replay_numpy(dt, horizon, idx, x, v, x_load, has_play, play, vs, q0, cog_k, cog_phase, coef,
                  u_in, kb_in, g, xs, vs_out) -> None:
    """The replay, one step of all windows at a time (see :func:`compiled.replay`, its compiled twin)."""
    a, kb, off, grav, cps, fc, fs, fa, gl, gc, kemf = coef.T
    x, v, x_load = x.copy(), v.copy(), x_load.copy()
    any_gl, any_gc, any_play = bool(np.any(gl)), bool(np.any(gc)), bool(np.any(has_play))
    any_emf = bool(np.any(kemf))
    # friction, per window: applied only where fc, fs or fa is set
    fric = (fc != 0) | (fs != 0) | (fa != 0)
    any_fric, any_fs = bool(np.any(fric)), bool(np.any(fs))
    for h in range(horizon):
        gk = g[idx]
        drive = a * u_in[idx] + kb * kb_in[idx] + off * gk + grav
        v_pred = v + dt * (drive - cps * gk * v)
        if any_emf:
            v_pred = np.where(kemf != 0, v_pred - dt * kemf * u_in[idx] * v, v_pred)
        if any_gl:
            v_pred = np.where(gl != 0, v_pred - dt * gk * gl * np.sin(x - q0), v_pred)
        if any_gc:
            v_pred = np.where(gc != 0, v_pred - dt * gk * gc * np.sin(cog_k * x - cog_phase), v_pred)
        if any_fric:
            # friction magnitude in the direction the axis would move (fa: forward/backward asymmetry)
            mag = fc + fa * np.sign(v_pred)
            if any_fs:
                mag = np.where(fs != 0, mag + fs * np.exp(-((v / vs) ** 2)), mag)
            step = dt * gk * mag
            # Implicit (Moreau) friction: stick when the other forces cannot overcome it. A negative
            # fitted friction (no friction in the data, noise) is applied explicitly instead.
            stick = (step > 0) & (np.abs(v_pred) <= step)
            sgn = np.where(step > 0, np.sign(v_pred), np.sign(v))
            v_new = np.where(fric, np.where(stick, 0.0, v_pred - step * sgn), v_pred)
        else:
            v_new = v_pred
        x = x + dt * 0.5 * (v + v_new)
        v = v_new
        idx = idx + 1
        if any_play:
            x_next = np.minimum(np.maximum(x_load, x - play), x + play)
            vs_out[:, h] = np.where(has_play, np.where(x_next != x_load, v, 0.0), v)  # the load moves only pushed
            x_load = np.where(has_play, x_next, x_load)
            xs[:, h] = np.where(has_play, x_load, x)
        else:
            xs[:, h] = x
            vs_out[:, h] = v


def _replay_group(built: list[dict], horizon: int, dt: float) -> list[dict[str, np.ndarray]]:
    xs, vs_out = _replay_stacked(_stack(built), horizon, dt)
    res, lo = [], 0
    for b in built:
        p, params, starts = b["p"], b["params"], b["starts"]
        hi = lo + starts.size
        ks = starts[:, None] + 1 + np.arange(horizon)[None, :]
        s, bias = params.sensor["scale_v"], params.sensor["bias_v"]
        res.append({"x_pred": xs[lo:hi], "x_true": p.ep.x[ks], "v_pred": s * vs_out[lo:hi] + bias,
                    "v_true": p.v_obs[ks], "k": ks})
        lo = hi
    return res


def score(p: Prepared, params: AxisParams, horizon: int) -> Scores:
    return score_many([(p, params)], horizon)[0]


def score_many(pairs, horizon: int) -> list[Scores]:
    """:func:`score` of many (episode, params) pairs, their open-loop windows replayed in one batch."""
    sims = simulate_many([(p, params, None, None) for p, params in pairs], horizon)
    out = []
    for (p, params), ms in zip(pairs, sims, strict=True):
        one = predict_one_step(p, params)
        out.append(Scores(
            one_sse={ch: float(np.sum((one[f"{ch}_pred"] - one[f"{ch}_true"]) ** 2)) for ch in ("x", "v")},
            one_n=int(one["k"].size),
            multi_sse={ch: float(np.sum((ms[f"{ch}_pred"] - ms[f"{ch}_true"]) ** 2)) for ch in ("x", "v")},
            multi_n=int(ms["k"].size),
        ))
    return out
