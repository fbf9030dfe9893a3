"""Residual diagnostics a physicist looks at (issue 28, item 3): they propose, the held-out test decides.

The one-step acceleration residual of a fitted axis model (measured − predicted, x-units/s², on the
regression rows) is examined against

* velocity: a step at v = 0 (dry / Coulomb friction), a slope (viscous: absorbed by the nominal
  refit, so a slope left over means a speed-dependent drag the model lacks), a dip towards 0 at low
  speed beyond the step (Stribeck);
* position: a sin/cos component (gravity on a rotary joint, x in rad) and a dominant period of the
  binned residual (cogging);
* the command's history: the correlation with the command change at each lag (a peak at a positive
  lag: delay or lag), and the residual at small |u| (deadband);
* direction reversals of the command: the mean |residual| just after a reversal against elsewhere
  (backlash: a dead zone at each reversal, not a lag).

Each statistic comes with a z-score (its size over a standard error inflated for the residual's
autocorrelation); a candidate is *proposed* when |z| ≥ :data:`PROPOSE_Z`. Proposals are reported
beside the held-out evidence; they decide nothing.
"""

from __future__ import annotations

import numpy as np

from hilstack.calibration import axis

#: |z| from which a diagnostic proposes its candidate.
PROPOSE_Z = 4.0


def _rows(preps, params) -> dict[str, np.ndarray]:
    theta = np.array([params.coef[n] for n in axis.coef_names(params.effects)])
    cols: dict[str, list] = {k: [] for k in ("r", "v", "x", "u", "du", "rev", "ep")}
    for i, p in enumerate(preps):
        X, y, k = axis.design(p, params)
        u = p.ep.u
        du = np.diff(u, prepend=u[0])
        su = np.sign(u)
        flips = np.flatnonzero(np.diff(su[su != 0]) != 0)  # command reversals (sign changes, zeros skipped)
        flips = np.flatnonzero(su != 0)[flips + 1] if flips.size else flips
        since = np.full(p.n, 10**9)
        for f in flips:
            since[f:] = np.minimum(since[f:], np.arange(p.n - f))
        cols["r"].append(y - X @ theta)
        cols["v"].append(axis.state_velocity(p, params.sensor)[k])
        cols["x"].append(p.ep.x[k])
        cols["u"].append(u[k])
        cols["du"].append(du)
        cols["rev"].append(since[k])
        cols["ep"].append(np.full(k.size, i))
    out = {k: np.concatenate(v) for k, v in cols.items() if k != "du"}
    out["du_list"] = cols["du"]
    out["k_list"] = [axis.design(p, params)[2] for p in preps]
    out["r_list"] = [out["r"][out["ep"] == i] for i in range(len(preps))]
    return out


def _z(diff: float, se: float) -> float:
    return float(diff / se) if se > 0 and np.isfinite(se) else 0.0


def residual_diagnostics(preps, params, period_s: float | None = None) -> dict:
    """Numbers for each diagnostic, with the candidates they propose (see the module docstring)."""
    from hilstack.calibration.selection import _autocorr_inflation

    d = _rows(preps, params)
    r, v, x, u = d["r"], d["v"], d["x"], d["u"]
    n = r.size
    out: dict = {"n_rows": int(n), "propose_z": PROPOSE_Z, "proposed": []}
    if n < 50:
        out["note"] = "too few regression rows for diagnostics"
        return out
    infl = _autocorr_inflation(r, 20)
    sd = float(np.std(r)) * np.sqrt(infl)

    def se(m):
        m = int(m)
        return sd / np.sqrt(max(m, 1))

    # velocity: dry step at v=0 (residual opposes motion: negative for v>0 when friction is missing)
    av = np.abs(v)
    lo = np.quantile(av, 0.25)
    pos, neg = (v > 0) & (av <= lo), (v < 0) & (av <= lo)
    step = float(r[pos].mean() - r[neg].mean()) if pos.any() and neg.any() else 0.0
    z_step = _z(step, sd * np.sqrt(1 / max(pos.sum(), 1) + 1 / max(neg.sum(), 1)))
    A = np.column_stack([np.ones(n), v, np.sign(v)])
    coef, *_ = np.linalg.lstsq(A, r, rcond=None)
    resid_v = r - A @ coef
    ss = float(np.sum((v - v.mean()) ** 2))
    z_slope = _z(float(coef[1]), sd / np.sqrt(ss) if ss > 0 else np.inf)
    # Stribeck: beyond the fitted step, low speeds still carry extra opposing residual
    slow, mid = av <= np.quantile(av, 0.2), (av > np.quantile(av, 0.4)) & (av <= np.quantile(av, 0.8))
    dip = float(np.mean(resid_v[slow] * np.sign(v[slow])) - np.mean(resid_v[mid] * np.sign(v[mid])))
    z_dip = _z(dip, np.sqrt(se(slow.sum()) ** 2 + se(mid.sum()) ** 2))
    out["velocity"] = {"dry_step": step, "z_dry_step": z_step, "viscous_slope": float(coef[1]),
                       "z_viscous_slope": z_slope, "low_speed_dip": dip, "z_low_speed_dip": z_dip}
    if abs(z_step) >= PROPOSE_Z:
        out["proposed"].append({"name": "coulomb_friction", "by": "step of the residual at v = 0", "z": z_step})
    if abs(z_dip) >= PROPOSE_Z:
        out["proposed"].append({"name": "stribeck_friction", "by": "extra residual at low speed", "z": z_dip})
    if abs(z_slope) >= PROPOSE_Z and abs(z_step) < PROPOSE_Z:  # with a step, the nominal viscous term is bent
        out["proposed"].append({"name": "viscous/speed-dependent drag", "by": "slope of the residual vs velocity",
                                "z": z_slope})
    # position: sin/cos (gravity) and dominant period (cogging)
    P = np.column_stack([np.ones(n), np.sin(x), np.cos(x)])
    pc, *_ = np.linalg.lstsq(P, r, rcond=None)
    amp = float(np.hypot(pc[1], pc[2]))
    r2_sin = 1.0 - float(np.sum((r - P @ pc) ** 2)) / max(float(np.sum((r - r.mean()) ** 2)), 1e-300)
    z_amp = _z(amp, sd * np.sqrt(2.0 / n))
    out["position"] = {"sin_amplitude": amp, "z_sin_amplitude": z_amp, "r2_sin": r2_sin,
                       "span": float(np.ptp(x))}
    if abs(z_amp) >= PROPOSE_Z and r2_sin >= 0.05 and np.ptp(x) >= 1.5:
        out["proposed"].append({"name": "gravity_load", "by": "sin(x) component of the residual", "z": z_amp})
    # command history: correlation with the command change per lag
    lags = np.arange(0, 31)
    cc = []
    for lg in lags:
        num, den = 0.0, 0.0
        for du, k, rr in zip(d["du_list"], d["k_list"], d["r_list"], strict=True):
            j = k - lg
            ok = j >= 0
            num += float(np.sum(rr[ok] * du[j[ok]]))
            den += float(np.sqrt(np.sum(rr[ok] ** 2) * np.sum(du[j[ok]] ** 2)) + 1e-300)
        cc.append(num / den if den > 0 else 0.0)
    cc = np.asarray(cc)
    peak = int(np.argmax(np.abs(cc)))
    z_cc = float(cc[peak] * np.sqrt(n / infl))
    out["command_history"] = {"xcorr": cc.tolist(), "peak_lag_samples": peak, "peak_corr": float(cc[peak]),
                              "z_peak": z_cc}
    if abs(z_cc) >= PROPOSE_Z:  # at lag 0 with a negative sign: the model responds before the axis does
        out["proposed"].append({"name": "delay or actuator_lag", "by": f"residual correlates with the command "
                                f"change {peak} sample(s) earlier", "z": z_cc})
    au = np.abs(u)
    small = au <= np.quantile(au, 0.15)
    if small.any() and (~small).any():
        db = float(np.mean(r[small] * np.sign(u[small])))
        z_db = _z(db, se(small.sum()))
        out["command_history"].update({"small_command_residual": db, "z_small_command": z_db})
        if z_db <= -PROPOSE_Z:
            out["proposed"].append({"name": "deadband", "by": "small commands move the axis less than modelled",
                                    "z": z_db})
    # reversals: |residual| just after a command reversal vs elsewhere
    near = d["rev"] <= 5
    if near.sum() >= 10 and (~near).sum() >= 10:
        ratio = float(np.mean(np.abs(r[near])) / max(np.mean(np.abs(r[~near])), 1e-300))
        z_rev = _z(float(np.mean(np.abs(r[near])) - np.mean(np.abs(r[~near]))), se(near.sum()))
        out["reversals"] = {"n_rows_after_reversal": int(near.sum()), "abs_residual_ratio": ratio, "z": z_rev}
        if z_rev >= PROPOSE_Z and abs(z_cc) < PROPOSE_Z:  # a delay disturbs every command change, not only reversals
            out["proposed"].append({"name": "backlash", "by": "larger residual just after command reversals",
                                    "z": z_rev})
    return out


def plot_diagnostics(path, diag_before: dict, preps, params) -> None:
    """Residual vs velocity, position, command, lag and time since reversal (one PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = _rows(preps, params)
    fig, ax = plt.subplots(1, 5, figsize=(20, 3.4))

    binned_plot(ax[0], d["v"], d["r"], "velocity: step=dry, slope=viscous, dip=Stribeck")
    ax[0].set_ylabel("mean residual [x/s²]")
    binned_plot(ax[1], d["x"], d["r"], "position: sin=gravity, periodic=cogging")
    binned_plot(ax[2], d["u"], d["r"], "command: flat near 0 = deadband")
    cc = diag_before.get("command_history", {}).get("xcorr", [])
    ax[3].stem(np.arange(len(cc)), cc)
    ax[3].set_xlabel("lag [samples]: peak = delay/lag")
    rev = np.minimum(d["rev"], 60)
    binned_plot(ax[4], rev, np.abs(d["r"]), "samples since command reversal (backlash)")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def binned_plot(a, xv, yv, label: str) -> None:
    """The mean of ``yv`` in 40 quantile bins of ``xv`` on axes ``a`` (a residual against a
    variable: the plot a physicist reads an effect from)."""
    edges = np.unique(np.quantile(xv, np.linspace(0, 1, 41)))
    mids, means = [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (xv >= lo) & (xv <= hi)
        if m.any():
            mids.append(0.5 * (lo + hi))
            means.append(yv[m].mean())
    a.plot(mids, means, ".-")
    a.axhline(0, color="k", lw=0.5)
    a.set_xlabel(label)
