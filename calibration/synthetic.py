"""Synthetic single-axis data with optional hidden effects, for tests and demos.

The truth is simulated in continuous time on a fine sub-step grid (``substeps`` per sample),
independently of the identification code's discretization, so a model that only matches the
generator's own discretization would not pass.

Physics (normalized by the inertia J): dv/dt = g·(a·ũ − c·v − F_fric(v) + d + cog(x)) + s_g,
dx/dt = v, with ũ the command after the hidden input-side effects. Units: x in m, u in V,
accelerations in m/s². With ``load_backlash`` the logged position is that of a load behind a
play of half-width h: x_load follows x only once x has moved h past it (a light load, whose
inertia and friction are part of the motor's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hilstack.calibration.data import Recording


@dataclass(frozen=True)
class SynthConfig:
    """Generator settings.

    Attributes:
        n_episodes: number of episodes.
        duration_s: length of each episode [s].
        period_s: sample period [s].
        substeps: integration sub-steps per sample.
        a: command gain k_u/J [m/s² per V].
        c_per_s: viscous coefficient b/J [1/s].
        u_max: command amplitude [V].
        x_noise_m: position noise std [m].
        v_noise_mps: velocity noise std [m/s] (measured velocity only).
        measure_velocity: log a velocity channel.
        effects: hidden effects, name -> parameters (see :data:`DEFAULTS`).
        excitation: "steps" (random steps and chirps), "sine" (slow zero-mean sines: velocity
            keeps the sign of the command, which makes Coulomb friction and a deadband look alike)
            or "drive" (forward-only speed steps, as a vehicle driving: position grows without bound).
        seed: random seed.
        x_quant: encoder resolution [x-units] (0: none); the logged position is rounded to it.
        velocity_from_differences: log a velocity channel computed as the finite difference of
            the (quantised) logged position, as many drives do: quantised in x_quant/period_s steps.
        n_rest: how many of the episodes are recorded at rest (zero command, the axis still).
    """

    n_episodes: int = 12
    duration_s: float = 6.0
    period_s: float = 0.01
    substeps: int = 10
    a: float = 10.0
    c_per_s: float = 5.0
    u_max: float = 1.5
    x_noise_m: float = 2e-4
    v_noise_mps: float = 0.005
    measure_velocity: bool = False
    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    excitation: str = "steps"
    seed: int = 0
    x_quant: float = 0.0
    velocity_from_differences: bool = False
    n_rest: int = 0


#: Default truth per effect (primary parameter first), used when a test names only the effect.
DEFAULTS: dict[str, dict[str, float]] = {
    "delay": {"delay_s": 0.03},
    "actuator_lag": {"tau_s": 0.05},
    "deadband": {"width_u": 0.3},
    "backlash": {"halfwidth_u": 0.25},
    "load_backlash": {"halfwidth_x": 0.01},
    "coulomb_friction": {"fc_acc": 2.0},
    "stribeck_friction": {"fs_extra_acc": 2.0, "vs": 0.1},
    "viscous_friction": {"c_per_s": 9.0},  # replaces the nominal c: a tuning error, absorbed by refit
    "force_offset": {"offset_acc": 1.0},
    "battery_sag": {"gain_per_rel_v": 1.0},
    "back_emf": {"kemf": 2.0},  # (a - kemf·v)·u
    "saturation": {"limit_u": 1.0},
    "payload_mass": {"mu_per_unit": 0.6},
    "slope": {"gravity_acc": 1.0},
    "sensor_bias": {"bias_v": 0.1},
    "sensor_scale": {"scale_v": 1.1},
    "asymmetric_friction": {"fa_acc": 0.8},  # on top of a Coulomb level (default 2.0 when not given)
    "gravity_load": {"gl_acc": 4.0, "q0_rad": 0.0},  # x in rad
    # outside the catalogue (for the black-box check): a tight spot, a force localized in position
    "tight_spot": {"amp_acc": 4.0, "x0_m": 0.0, "width_m": 0.1},
    "cogging": {"gc_acc": 3.0, "k_rad_per_x": 4 * math.pi, "phase_rad": 0.0},  # -gc·sin(k·x - phase), period 0.5
}


def truth(name: str, cfg: SynthConfig | None = None) -> dict[str, float]:
    if cfg is not None and name in cfg.effects:
        return {**DEFAULTS.get(name, {}), **cfg.effects[name]}
    return dict(DEFAULTS[name])


def _commands(rng: np.random.Generator, n: int, period_s: float, u_max: float, kind: str = "steps") -> np.ndarray:
    """Random steps (hold 0.1-0.5 s) mixed with short chirps: rich in level and in frequency."""
    if kind == "sine":
        t = np.arange(n) * period_s
        return rng.uniform(0.5, 1.0) * u_max * np.sin(2 * np.pi * rng.uniform(0.2, 0.5) * t + rng.uniform(0, 6.3))
    if kind == "drive":
        u = np.empty(n)
        k = 0
        while k < n:
            length = int(rng.uniform(0.3, 1.0) / period_s)
            u[k : k + length] = rng.uniform(0.0, u_max) if rng.random() > 0.15 else 0.0
            k += length
        return u
    u = np.empty(n)
    k = 0
    while k < n:
        if rng.random() < 0.15:
            length = int(rng.uniform(0.5, 1.5) / period_s)
            t = np.arange(length) * period_s
            f0, f1 = 0.5, rng.uniform(3, 8)
            phase = 2 * np.pi * (f0 * t + 0.5 * (f1 - f0) / max(t[-1], period_s) * t**2)
            seg = rng.uniform(0.3, 1.0) * u_max * np.sin(phase) + rng.uniform(-0.3, 0.3) * u_max
        else:
            length = int(rng.uniform(0.1, 0.5) / period_s)
            seg = np.full(length, rng.uniform(-u_max, u_max))
        u[k : k + length] = seg[: n - k]
        k += length
    return u


def generate(cfg: SynthConfig) -> list[Recording]:
    """Simulate ``cfg.n_episodes`` episodes; returns Episodes with ``meta['truth']``."""
    rng = np.random.default_rng(cfg.seed)
    n = int(round(cfg.duration_s / cfg.period_s))
    E, S = cfg.n_episodes, cfg.substeps
    dts = cfg.period_s / S
    eff = {k: truth(k, cfg) for k in cfg.effects}
    u = np.stack([_commands(rng, n, cfg.period_s, cfg.u_max, cfg.excitation) for _ in range(E)])  # (E, n)
    u[E - cfg.n_rest:] = 0.0  # episodes at rest: nothing commanded

    # Battery: each episode starts at a random charge and sags while driving.
    vbat = None
    if "battery_sag" in eff:
        start = rng.uniform(7.4, 8.4, size=(E, 1))
        drain = np.cumsum(np.abs(u), axis=1) * cfg.period_s
        vbat = start - 0.6 * drain / max(drain[:, -1].max(), 1e-9) + 0.02 * rng.standard_normal((E, n))
    payload = None
    if "payload_mass" in eff:
        payload = np.repeat((np.arange(E) % 2).astype(float)[:, None], n, axis=1)

    # Input chain on the sub-step grid (the command is a ZOH of the logged samples).
    us = np.repeat(u, S, axis=1)
    if "delay" in eff:
        d = int(round(eff["delay"]["delay_s"] / dts))
        us = np.concatenate([np.repeat(us[:, :1], d, axis=1), us[:, : us.shape[1] - d]], axis=1)
    if "saturation" in eff:
        us = np.clip(us, -eff["saturation"]["limit_u"], eff["saturation"]["limit_u"])
    if "deadband" in eff:
        w = eff["deadband"]["width_u"]
        us = np.sign(us) * np.maximum(np.abs(us) - w, 0.0)
    if "backlash" in eff:
        h = eff["backlash"]["halfwidth_u"]
        y = us[:, 0].copy()
        out = np.empty_like(us)
        for k in range(us.shape[1]):
            y = np.minimum(np.maximum(y, us[:, k] - h), us[:, k] + h)
            out[:, k] = y
        us = out
    if vbat is not None:
        kappa = eff["battery_sag"]["gain_per_rel_v"]
        vref = 7.9
        us = us * (1 + kappa * (np.repeat(vbat, S, axis=1) - vref) / vref)

    c = eff.get("viscous_friction", {}).get("c_per_s", cfg.c_per_s)
    fc = eff.get("coulomb_friction", {}).get("fc_acc", 0.0)
    fa = eff.get("asymmetric_friction", {}).get("fa_acc", 0.0)
    if fa and "coulomb_friction" not in eff:
        fc = DEFAULTS["coulomb_friction"]["fc_acc"]
    gl = eff.get("gravity_load", {}).get("gl_acc", 0.0)
    q0 = eff.get("gravity_load", {}).get("q0_rad", 0.0)
    fs = eff.get("stribeck_friction", {}).get("fs_extra_acc", 0.0)
    vs = eff.get("stribeck_friction", {}).get("vs", 1.0)
    if "stribeck_friction" in eff and "coulomb_friction" not in eff:
        fc = 0.5 * fs  # Stribeck needs a Coulomb level to decay to
    d_off = eff.get("force_offset", {}).get("offset_acc", 0.0)
    slope = eff.get("slope", {}).get("gravity_acc", 0.0)
    cog_amp = eff.get("cogging", {}).get("gc_acc", 0.0)
    cog_k = eff.get("cogging", {}).get("k_rad_per_x", 1.0)
    cog_phase = eff.get("cogging", {}).get("phase_rad", 0.0)
    ts = eff.get("tight_spot", {})
    ts_amp, ts_x0, ts_w = ts.get("amp_acc", 0.0), ts.get("x0_m", 0.0), ts.get("width_m", 1.0)
    g = np.ones(E) if payload is None else 1.0 / (1.0 + eff["payload_mass"]["mu_per_unit"] * payload[:, 0])
    tau = eff.get("actuator_lag", {}).get("tau_s", 0.0)
    alpha = math.exp(-dts / tau) if tau > 0 else 0.0

    hl = eff.get("load_backlash", {}).get("halfwidth_x", 0.0)
    kemf = eff.get("back_emf", {}).get("kemf", 0.0)

    x = np.zeros(E)
    v = np.zeros(E)
    x_load = x - hl  # the load in contact as after a forward move (what the model assumes at rest)
    v_load = v.copy()
    f_act = us[:, 0].copy()
    xs = np.empty((E, n))
    vs_true = np.empty((E, n))
    for k in range(n):
        xs[:, k] = x if not hl else x_load
        vs_true[:, k] = v if not hl else v_load
        for j in range(S):
            i = k * S + j
            f_act = alpha * f_act + (1 - alpha) * us[:, i] if tau > 0 else us[:, i]
            drive = g * (cfg.a * f_act - kemf * f_act * v - c * v + d_off - cog_amp * np.sin(cog_k * x - cog_phase)
                         - gl * np.sin(x - q0) - ts_amp * np.exp(-(((x - ts_x0) / ts_w) ** 2))) + slope
            v_pred = v + dts * drive
            step = dts * g * (fc + fa * np.sign(v_pred) + fs * np.exp(-((v / vs) ** 2)))
            v_new = np.where(np.abs(v_pred) <= step, 0.0, v_pred - step * np.sign(v_pred))
            x = x + 0.5 * dts * (v + v_new)
            v = v_new
            if hl:
                # play operator on the sub-step grid: the load moves only while pushed at one end of the gap
                x_next = np.minimum(np.maximum(x_load, x - hl), x + hl)
                v_load = (x_next - x_load) / dts
                x_load = x_next

    t = np.arange(n) * cfg.period_s
    episodes = []
    sb = eff.get("sensor_bias", {}).get("bias_v", 0.0)
    ss = eff.get("sensor_scale", {}).get("scale_v", 1.0)
    measure_v = cfg.measure_velocity or "sensor_bias" in eff or "sensor_scale" in eff
    for e in range(E):
        x_meas = xs[e] + cfg.x_noise_m * rng.standard_normal(n)
        if cfg.x_quant > 0:
            x_meas = np.round(x_meas / cfg.x_quant) * cfg.x_quant
        v_meas = ss * vs_true[e] + sb + cfg.v_noise_mps * rng.standard_normal(n) if measure_v else None
        if cfg.velocity_from_differences:
            v_meas = np.concatenate([[0.0], np.diff(x_meas) / cfg.period_s])
        episodes.append(
            Recording(
                name=f"synthetic#episode={e}",
                t_s=t.copy(),
                u=u[e].copy(),
                x=x_meas,
                v_meas=v_meas,
                vbat_v=None if vbat is None else vbat[e].copy(),
                payload=None if payload is None else payload[e].copy(),
                meta={"truth": eff, "source": "synthetic"},
            )
        )
    return episodes


def write_csv(episodes: list[Recording], path: str | Path) -> Path:
    """One CSV with an ``episode`` column; columns time, volts, position[, velocity, vbat, payload]."""
    import pandas as pd

    frames = []
    for i, e in enumerate(episodes):
        cols = {"episode": i, "time": e.t_s, "volts": e.u, "position": e.x}
        if e.v_meas is not None:
            cols["velocity"] = e.v_meas
        if e.vbat_v is not None:
            cols["vbat"] = e.vbat_v
        if e.payload is not None:
            cols["payload"] = e.payload
        frames.append(pd.DataFrame(cols))
    path = Path(path)
    pd.concat(frames).to_csv(path, index=False)
    return path
