"""run_calibration: data → selection → augmented model → before/after report (JSON, Markdown, PNG)."""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from hilstack.calibration import axis
from hilstack.calibration.data import (
    DataError,
    Recording,
    harmonize_rates,
    load_episodes,
    segment_episodes,
    summarize,
)
from hilstack.calibration.model_api import (
    CountsRollouts,
    DescribesVelocity,
    ExportsAugmented,
    ExportsSimParams,
    LoadsEpisodes,
    OwnDetectionLimits,
    OwnPlots,
)
from hilstack.calibration.models import FittedAxis, get_model, save_model
from hilstack.calibration.selection import (
    SelectionConfig,
    blackbox_check,
    detection_limits,
    heldout_gain,
    select_effects,
)


def _nrmse_table(scores: list[axis.Scores], sd: dict[str, dict[str, float]], n_boot: int, seed: int) -> dict:
    """NRMSE on a set of episodes, per channel and mean, with episode-bootstrap 95 % intervals.

    ``sd`` (from the model's ``channel_sd``): for the axis, one-step is the RMSE of the
    predicted sample at k+1 over the std of the channel's increment, multi-step the RMSE of
    H-step open-loop windows over the std of the channel.
    """
    channels = list(sd["one"])
    # (squared errors per channel, samples) of each episode, per kind
    errors = {"one": [(s.one_sse, s.one_n) for s in scores], "multi": [(s.multi_sse, s.multi_n) for s in scores]}

    def table(idx: np.ndarray) -> dict:
        out = {}
        for kind in ("one", "multi"):
            per = {}
            for ch in channels:
                sse = sum(errors[kind][i][0][ch] for i in idx)
                n = sum(errors[kind][i][1] for i in idx)
                per[ch] = math.sqrt(sse / max(n, 1)) / sd[kind][ch]
            out[kind] = {"per_channel": per, "mean": float(np.mean(list(per.values())))}
        return out

    idx_all = np.arange(len(scores))
    point = table(idx_all)
    rng = np.random.default_rng(seed + 104729)
    boots = [table(rng.integers(0, len(scores), len(scores))) for _ in range(n_boot)] if len(scores) > 1 else []

    def interval(kind, key, ch=None):
        if not boots:
            return None
        vals = [b[kind]["mean"] if ch is None else b[kind]["per_channel"][ch] for b in boots]
        return [float(np.percentile(vals, 2.5)), float(np.percentile(vals, 97.5))]

    res = {}
    for kind, label in (("one", "one_step_nrmse"), ("multi", "multi_step_nrmse")):
        res[label] = {
            "mean": point[kind]["mean"],
            "mean_interval": interval(kind, "mean"),
            "per_channel": point[kind]["per_channel"],
            "per_channel_interval": {ch: interval(kind, "pc", ch) for ch in channels},
        }
    return res


def _clean(o):
    """JSON-safe (inf → null, numpy → python)."""
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_clean(v) for v in o]
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    if isinstance(o, np.integer | np.bool_):
        return o.item()
    if isinstance(o, float | np.floating):
        f = float(o)
        return f if math.isfinite(f) else None
    return o


def run_calibration(
    data_path: str | Path | list[Recording],
    model: str = "axis",
    column_map: str | dict | Path | None = None,
    out_dir: str | Path = "calibration_out",
    seed: int = 0,
    progress: bool = True,
    k_u: float | None = None,
    config: SelectionConfig | None = None,
    sg_window: int | None = None,
    plots: bool = True,
    model_options: dict | None = None,
    robot: str | None = None,
) -> dict:
    """Calibrate a nominal model against measured episodes and write the report.

    Args:
        data_path: CSV/Parquet file, directory, .mcap, or a list of Episodes.
        model: nominal model name (``axis``, ``velociroach``, ``checkpoint`` with
            ``model_options={"checkpoint": PATH}``) or the path of a learned checkpoint (``.pt``).
        column_map: ``t=time,u=volts,x=position[,v=..,vbat=..,m=..]`` or a YAML path/dict.
        out_dir: where report.json, report.md, model.json and the PNGs go.
        seed: seed of the episode split and bootstraps.
        progress: print progress to stderr.
        k_u: known actuator gain (force per command unit, e.g. N/V) for physical parameters.
        config: statistical settings.
        sg_window: Savitzky-Golay window [samples] for derived velocity (default ≈ 30 ms).
        plots: write PNG plots.
        model_options: extra keyword arguments of the model (velociroach: ``nominal``, a robot
            config YAML or a dict of VelociRoachParams fields).
        robot: MCAP input: which robot's states, when the recording holds several.

    Returns:
        The report dict (also written to ``out_dir/report.json``).
    """
    t0 = time.time()
    cfg = config or SelectionConfig()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DataError(f"--out {out} is an existing file, not a directory; give a directory for the report "
                        "(the file is left as it is)")
    out.mkdir(parents=True, exist_ok=True)

    def log(msg: str) -> None:
        if progress:
            print(f"[calibrate {time.time() - t0:6.1f}s] {msg}", file=sys.stderr, flush=True)

    warnings: list[str] = []

    def warn(msg: str) -> None:
        warnings.append(msg)
        log(f"warning: {msg}")

    opts = {"k_u": k_u, "sg_window": sg_window} if model == "axis" else {}
    opts.update(model_options or {})
    nominal_model = get_model(model, **opts)
    if isinstance(data_path, list):
        episodes = list(data_path)
    elif isinstance(nominal_model, LoadsEpisodes):  # the model knows its channels (checkpoint)
        episodes = nominal_model.load_episodes(data_path, column_map, robot=robot)
    else:
        episodes = load_episodes(data_path, column_map, robot=robot, warn=warn)
    if not episodes:
        raise DataError("no episode to calibrate on")
    source = "episodes" if isinstance(data_path, list) else str(data_path)
    log(f"loaded {len(episodes)} episode(s) from {source}")
    plan = None
    if nominal_model.segmentable:
        episodes = harmonize_rates(episodes, warn)
        episodes = _drop_motionless(nominal_model, episodes, warn)
        period = episodes[0].period_s
        h_steps = max(2, int(round(cfg.horizon_s / period)))
        episodes, plan = segment_episodes(episodes, cfg.min_episodes, h_steps,
                                          axis.segment_margin(period, sg_window), cfg.test_fraction)
        if plan.segmented:
            log(plan.note)
            episodes = _drop_motionless(nominal_model, episodes, warn)
        if plan.horizon_steps < h_steps:
            cfg = replace(cfg, horizon_s=plan.horizon_steps * period)
            warn(f"short recording: open-loop horizon shortened from {h_steps} to {plan.horizon_steps} samples "
                 "so that it can be cut into enough segments")
    preps = nominal_model.prepare(episodes)

    sel = select_effects(nominal_model, preps, cfg, seed=seed, log=log)
    resolution = _resolution(nominal_model, preps, sel, cfg, warn)
    is_axis = isinstance(sel.final, FittedAxis)
    pool_idx = np.concatenate(sel.folds)
    pool = [preps[i] for i in pool_idx]
    test = [preps[i] for i in sel.test_idx]
    log("scoring the locked test set")
    before_scores = [nominal_model.score(p, sel.nominal, sel.horizon) for p in test]
    after_scores = [nominal_model.score(p, sel.final, sel.horizon) for p in test]
    sd = nominal_model.channel_sd(test)
    before = _nrmse_table(before_scores, sd, 500, seed)
    after = _nrmse_table(after_scores, sd, 500, seed)
    verdict, confirmation = _verdict(nominal_model, sel, test, before, after)
    if verdict == NOT_CONFIRMED:
        warn(f"{', '.join(r.name for r in sel.accepted)} passed on the training folds but {confirmation['reason']}")
    log("black-box check of the remaining residual")
    bb = blackbox_check(preps, sel.folds, sel.final, cfg, seed, model=nominal_model)
    candidates, _ = nominal_model.candidate_effects(preps)
    if isinstance(nominal_model, OwnDetectionLimits):
        det = nominal_model.detection_limits(pool, sel.final, candidates, sel.skipped, cfg)
    else:
        det = detection_limits(pool, sel.final, candidates, sel.skipped, cfg)

    diagnostics = None
    if is_axis:
        from hilstack.calibration.diagnostics import residual_diagnostics

        log("residual diagnostics")
        diagnostics = {"nominal": residual_diagnostics(pool, sel.nominal.params),
                       "final": residual_diagnostics(pool, sel.final.params)}
    effects_doc = []
    amb_names = {n for a in sel.ambiguous for n in a["effects"]}
    for r in sel.accepted:
        spec = nominal_model.catalogue[r.name]
        effects_doc.append({
            "name": r.name,
            "description": spec.description,
            "params": sel.final.effect_params(r.name),
            "primary": spec.primary,
            "unit": spec.unit,
            "no_effect": spec.no_effect,
            "interval": r.interval,
            "heldout_gain": r.gain,
            "evidence": r.evidence.to_dict() if r.evidence is not None else None,
            "p_value": r.p_value,
            "stability": r.stability,
            "ambiguous": r.name in amb_names,
        })
    report = {
        "model": model,
        "data": {**summarize(episodes), "segmented": bool(plan and plan.segmented), "resolution": resolution,
                 "segmentation_note": plan.note if plan else None,
                 "velocity_source": (nominal_model.velocity_source if isinstance(nominal_model, DescribesVelocity)
                                     else _velocity_source(preps[0]))},
        "folds": {"k": len(sel.folds), "test_episodes": [episodes[i].name for i in sel.test_idx],
                  "fold_episodes": [[episodes[i].name for i in f] for f in sel.folds],
                  "horizon_steps": sel.horizon, "horizon_s": sel.horizon * preps[0].period_s},
        "config": cfg.__dict__,
        "seed": seed,
        "verdict": verdict,
        "confirmation": confirmation,
        "effects": effects_doc,
        "ambiguous": sel.ambiguous,
        "findings": sel.findings,
        "diagnostics": diagnostics,
        "unexplained_structure": bb["unexplained_structure"],
        "blackbox": bb,
        "detection_limit": det,
        "before": before,
        "after": after,
        "nominal_params": sel.nominal.params.coef if is_axis else sel.nominal.to_dict(),
        "final_params": sel.final.params.to_dict() if is_axis else sel.final.to_dict(),
        "physical_params": ({"before": sel.nominal.params.physical(), "after": sel.final.params.physical()}
                            if is_axis else {"before": None, "after": None}),
        "channels": {"one_step": "per-period increment" if not is_axis else "one-step prediction",
                     "multi_step": "whole-episode open-loop replay" if not is_axis
                     else f"{sel.horizon}-step open-loop windows"},
        "not_tested": sel.skipped,
        "rounds": sel.rounds,
        "warnings": warnings,
        "elapsed_s": time.time() - t0,
    }
    if isinstance(nominal_model, ExportsAugmented):
        report["augmented_model"] = nominal_model.export_augmented(out, sel.final, report, test)
        report["channels"] = {"one_step": "one-step prediction from the logged state",
                              "multi_step": f"{sel.horizon}-step open-loop windows (logged actions replayed)"}
    if isinstance(nominal_model, ExportsSimParams):
        report["closing_the_loop"] = nominal_model.export(out, sel.final, report)
    if isinstance(nominal_model, CountsRollouts):
        report["sim_rollouts"] = nominal_model.n_rollouts
    report = _clean(report)
    save_model(sel.final, out / "model.json", extra={"source": source, "verdict": report["verdict"]})
    (out / "report.json").write_text(json.dumps(report, indent=2))
    if plots:
        log("plots")
        if isinstance(nominal_model, OwnPlots):
            nominal_model.plots(out, sel, preps, pool, test)
            _candidate_plot(out, sel)
        else:
            _plots(out, sel, preps, pool, test)
            from hilstack.calibration.diagnostics import plot_diagnostics

            plot_diagnostics(out / "residual_diagnostics.png", diagnostics["nominal"], pool, sel.nominal.params)
    (out / "report.md").write_text(render_markdown(report))
    log(f"done: verdict {report['verdict']}, multi-step NRMSE {before['multi_step_nrmse']['mean']:.3f} -> "
        f"{after['multi_step_nrmse']['mean']:.3f}")
    return report


#: Verdict when effects passed the selection but the locked test set does not confirm them.
NOT_CONFIRMED = "not confirmed on held-out data"


def _verdict(model, sel, test: list, before: dict, after: dict) -> tuple[str, dict]:
    """``found`` only when the locked test set confirms the accepted effects.

    Confirmed means: the selection score on the locked test episodes improves (held-out gain > 0,
    the same per-channel score the selection used) and the multi-step NRMSE does not rise.
    Otherwise the verdict is :data:`NOT_CONFIRMED`, so a report can never claim an effect that
    made the held-out error worse.
    """
    if not sel.accepted:
        return "none", {"confirmed": None, "reason": "no effect accepted"}
    if not test:
        return NOT_CONFIRMED, {"confirmed": False, "reason": "there is no locked test set (too few episodes)"}
    lb = np.array([model.episode_loss(p, sel.nominal, sel.horizon, sel.norms) for p in test])
    la = np.array([model.episode_loss(p, sel.final, sel.horizon, sel.norms) for p in test])
    gain = heldout_gain(lb, la)
    mb, ma = before["multi_step_nrmse"]["mean"], after["multi_step_nrmse"]["mean"]
    doc = {"test_gain": gain, "multi_step_nrmse_before": mb, "multi_step_nrmse_after": ma}
    if gain > 0 and ma <= mb:
        return "found", {**doc, "confirmed": True, "reason": "the locked test error fell"}
    why = (f"the locked test score got worse (gain {gain:+.3f})" if gain <= 0 else
           f"the locked test multi-step NRMSE rose from {mb:.4g} to {ma:.4g}")
    return NOT_CONFIRMED, {**doc, "confirmed": False, "reason": why}


def _resolution(model, preps, sel, cfg, warn) -> dict:
    """What the amount of data can resolve at all, consistent with the evidence rule.

    The evidence levels come from a block bootstrap over held-out units: with fewer than
    :data:`MIN_HELDOUT_UNITS` of them (or fewer blocks than that) the bootstrap interval is
    meaningless, so nothing can reach "moderate".
    """
    n_units = int(sum(len(f) for f in sel.folds))
    block = int(sel.folds.block)
    n_blocks = n_units // max(1, block)
    doc = {"heldout_units": n_units, "bootstrap_block": block, "bootstrap_blocks": n_blocks,
           "can_accept": n_blocks >= MIN_HELDOUT_UNITS, "locked_test_units": int(len(sel.test_idx))}
    if n_blocks < MIN_HELDOUT_UNITS:
        warn(f"only {n_blocks} independent held-out block(s) of {block} unit(s): the bootstrap interval of the "
             f"held-out gain needs at least {MIN_HELDOUT_UNITS}; no effect can reach moderate evidence; record more "
             "episodes or a longer recording")
    return doc


#: Fewest held-out bootstrap blocks for an evidence level above "weak" to mean anything.
MIN_HELDOUT_UNITS = 4


def _drop_motionless(model, episodes: list[Recording], warn) -> list[Recording]:
    """Skip episodes in which the axis never moves (no regression row), with a warning.

    Slow friction tests and idle stretches produce such episodes; they say nothing about the
    dynamics the effects act on, and an empty episode cannot be scored.
    """
    preps = model.prepare(episodes)
    keep = []
    for e, p in zip(episodes, preps, strict=True):
        n_rows = int(np.count_nonzero(p.moving[p.margin: p.n - p.margin - 1]))
        if n_rows < MIN_MOVING_ROWS:
            warn(f"{e.name}: skipped, the axis barely moves ({n_rows} samples above the standstill threshold "
                 f"{p.v_min:.3g} x/s; need {MIN_MOVING_ROWS})")
        else:
            keep.append(e)
    if not keep:
        raise DataError(f"no episode with motion: in all {len(episodes)} episode(s) the axis stays below the "
                        "standstill threshold; check the position column and its units, or record with motion")
    return keep


#: Fewest samples in motion an episode must have to be used (else it is skipped with a warning).
MIN_MOVING_ROWS = 20


def _velocity_source(p) -> str:
    if not isinstance(p, axis.Prepared):
        return "recorded state (world velocity rotated into the body frame; crank encoders)"
    if p.kernel is None:
        return "measured"
    return f"Savitzky-Golay derivative of position (quadratic, window {p.window} samples)"


def _num(v, fmt: str = ".3g") -> str:
    """A number for the report, or "n/a" when it is missing or not finite (constant data gives None)."""
    return "n/a" if v is None or not np.isfinite(v) else format(v, fmt)


def _fmt_iv(iv) -> str:
    return "" if not iv else f" [{iv[0]:.3g}, {iv[1]:.3g}]"


def render_markdown(r: dict) -> str:
    lines = [f"# Calibration report: model `{r['model']}`", ""]
    d = r["data"]
    lines += [f"Data: {d['n_episodes']} episodes, {d['n_samples']} samples at {d['period_s']:.4g} s "
              f"({d['duration_s']:.1f} s); velocity: {d['velocity_source']}."]
    if d.get("segmentation_note"):
        lines += ["", f"Note: {d['segmentation_note']}."]
    lines += ["", f"**Verdict: {r['verdict']}**" + ("" if r["effects"] else " (nothing found)"), ""]
    if r["verdict"] == NOT_CONFIRMED:
        lines += [f"The effects below passed the tests on the training folds, but {r['confirmation']['reason']}: "
                  "they are not claimed.", ""]
    if r.get("warnings"):
        lines += ["Warnings:", ""] + [f"- {w}" for w in r["warnings"]] + [""]
    if r["effects"]:
        lines += ["| effect | parameters | 95% interval (primary) | evidence | held-out gain [95% block bootstrap] "
                  "| stability |", "|---|---|---|---|---|---|"]
        for e in r["effects"]:
            ps = ", ".join(f"{k}={v:.4g}" for k, v in e["params"].items() if v is not None)
            evd = e.get("evidence") or {}
            lines.append(f"| {e['name']}{' (ambiguous)' if e['ambiguous'] else ''} | {ps} | "
                         f"{e['primary']}{_fmt_iv(e['interval'])} | {evd.get('level', 'n/a')} | "
                         f"{e['heldout_gain']:.3f}{_fmt_iv(evd.get('interval'))} | {_num(e['stability'], '.2f')} |")
    if r.get("findings"):
        lines += ["", "Weaker findings (not added to the model; evidence with its numbers):", ""]
        for f in r["findings"]:
            lines.append(f"- {f['name']}: {f['level']}, held-out gain {f['heldout_gain']:+.3f}"
                         f"{_fmt_iv(f['interval'])}, {f['p_positive']:.0%} of bootstrap replicates positive"
                         + (f"; {f['why_not_accepted']}" if f.get("why_not_accepted") else ""))
    if r["ambiguous"]:
        lines += ["", "Ambiguous (look-alikes the data cannot separate):"]
        for a in r["ambiguous"]:
            how = ("identical held-out fit" if a.get("identical_fit") else
                   f"separation evidence {(a.get('evidence_separation') or {}).get('level', 'n/a')}")
            lines.append(f"- {a['effects'][0]} vs {a['effects'][1]} (chose {a['chosen']}, {how}); to separate: "
                         f"{a['excitation']}")
    chans = list(r["before"]["multi_step_nrmse"]["per_channel"])
    lines += ["", "Locked test set (NRMSE, 95% episode-bootstrap interval):", "",
              "| | one-step mean | multi-step mean | " + " | ".join(f"multi-step {c}" for c in chans) + " |",
              "|---|---|---|" + "---|" * len(chans)]
    for k in ("before", "after"):
        t = r[k]
        lines.append(f"| {k} | {_num(t['one_step_nrmse']['mean'], '.4f')}{_fmt_iv(t['one_step_nrmse']['mean_interval'])}"
                     f" | {_num(t['multi_step_nrmse']['mean'], '.4f')}{_fmt_iv(t['multi_step_nrmse']['mean_interval'])} | "
                     + " | ".join(_num(t['multi_step_nrmse']['per_channel'][c], '.4f') for c in chans) + " |")
    bb = r["blackbox"]
    lines += ["", f"Unexplained structure: **{r['unexplained_structure']}** (black-box held-out R² "
              f"{_num(bb['heldout_r2'], '.3f')}, p={_num(bb['p_value'], '.2g')}; thresholds R² ≥ {bb['threshold_r2']}, p < {bb['alpha']})."]
    if r.get("diagnostics"):
        lines += ["", "Residual diagnostics (they propose; the held-out evidence decides; plot "
                  "residual_diagnostics.png):", ""]
        for stage in ("nominal", "final"):
            dg = r["diagnostics"][stage]
            props = ", ".join(f"{q['name']} ({q['by']}, z={q['z']:.1f})" for q in dg.get("proposed", [])) or "nothing"
            lines.append(f"- residual of the {stage} model proposes: {props}")
    lines += ["", "Detection limits (smallest primary-parameter value the data could have revealed):", ""]
    for name, e in r["detection_limit"]["per_effect"].items():
        val = "n/a" if e["value"] is None else f"{e['value']:.3g} {e['unit']}"
        lines.append(f"- {name} ({e['param']}): {val} — {e.get('note', '')}")
    if r.get("closing_the_loop"):
        c = r["closing_the_loop"]
        lines += ["", f"Closing the loop: calibrated sim config `{c['sim_params_yaml']}` (params.sim overrides "
                  f"{c['sim_overrides']}; not sim settings: {c['not_sim_settings'] or 'none'})."]
    if r.get("augmented_model"):
        a = r["augmented_model"]
        extras = ", ".join(f"{e['name']} (columns {e['columns']})" for e in a["extra_inputs"]) or "none"
        lines += ["", f"Augmented model: `{a['path']}` (checkpoint `{a['checkpoint']}` retrained with extra inputs: "
                  f"{extras}; {a['retrained']['epochs']} epochs from {a['retrained']['init']})."]
        if a.get("checkpoint_as_is"):
            c = a["checkpoint_as_is"]
            lines.append(f"The checkpoint as given (not retrained) on the locked test set: one-step NRMSE "
                         f"{c['one_step_nrmse']['mean']:.4f}, multi-step {c['multi_step_nrmse']['mean']:.4f}.")
    if r["physical_params"]["after"]:
        lines += ["", "Physical parameters (k_u given):", ""]
        for k in ("before", "after"):
            lines.append(f"- {k}: " + ", ".join(f"{n}={v:.4g}" for n, v in r["physical_params"][k].items()))
    lines += ["", "Not tested: " + "; ".join(f"{k}: {v}" for k, v in r["not_tested"].items()), ""]
    plots = ("residual_before_after.png, candidates.png" if r.get("closing_the_loop") or r.get("augmented_model")
             else "residual_before_after.png, diagnostics.png, residual_diagnostics.png, candidates.png")
    lines += [f"Plots: {plots}", ""]
    return "\n".join(lines)


def _plots(out: Path, sel, preps, pool, test) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nom, fin = sel.nominal.params, sel.final.params
    p = test[0] if test else pool[0]
    fig, ax = plt.subplots(3, 1, figsize=(9, 8), sharex=False)
    for params, label in ((nom, "before (nominal)"), (fin, "after (augmented)")):
        one = axis.predict_one_step(p, params)
        ax[0].plot(p.ep.t_s[one["k"]], one["v_true"] - one["v_pred"], lw=0.7, label=label)
        h = min(p.n - 2 * p.margin - 2, max(sel.horizon * 4, sel.horizon))
        sim = axis.simulate_windows(p, params, h, starts=np.array([p.margin]))
        ax[1].plot(p.ep.t_s[sim["k"][0]], sim["x_pred"][0], lw=1.0, label=label)
        ax[2].plot(p.ep.t_s[sim["k"][0]], sim["x_true"][0] - sim["x_pred"][0], lw=1.0, label=label)
    ax[1].plot(p.ep.t_s[sim["k"][0]], sim["x_true"][0], "k", lw=0.8, label="measured")
    ax[0].set_ylabel("one-step v residual")
    ax[1].set_ylabel("x, open loop")
    ax[2].set_ylabel("x error, open loop")
    ax[2].set_xlabel("t [s]")
    for a in ax:
        a.legend(fontsize=7)
    ax[0].set_title(f"test episode {p.ep.name}")
    fig.tight_layout()
    fig.savefig(out / "residual_before_after.png", dpi=90)
    plt.close(fig)

    # Diagnostics on the nominal residual of the training pool.
    V, U, R, DU, VB = [], [], [], [], []
    for q in pool:
        X, y, k = axis.design(q, nom)
        theta = np.array([nom.coef[n] for n in axis.coef_names(nom.effects)])
        R.append(y - X @ theta)
        V.append(q.v_obs[k])
        U.append(q.ep.u[k])
        DU.append(np.diff(q.ep.u, prepend=q.ep.u[0])[k])
        if q.ep.vbat_v is not None:
            VB.append(q.ep.vbat_v[k])
    R, V, U = np.concatenate(R), np.concatenate(V), np.concatenate(U)
    n_pan = 4 if VB else 3
    from hilstack.calibration.diagnostics import binned_plot

    fig, ax = plt.subplots(1, n_pan, figsize=(4 * n_pan, 3.4))

    binned_plot(ax[0], V, R, "velocity (coulomb/stribeck/viscous)")
    ax[0].set_ylabel("mean nominal residual [x/s²]")
    binned_plot(ax[1], U, R, "command (deadband/saturation)")
    # Cross-correlation with the command rate: a peak at positive lag means delay/lag.
    du = np.concatenate(DU)
    lags = np.arange(-10, 31)
    cc = []
    for lg in lags:  # residual at k+lg against the command change at k
        r_part, d_part = (R[lg:], du[: du.size - lg]) if lg >= 0 else (R[:lg], du[-lg:])
        cc.append(np.corrcoef(r_part, d_part)[0, 1])
    ax[2].stem(lags, cc)
    ax[2].set_xlabel("lag [samples] (residual after command change)")
    ax[2].set_ylabel("corr(residual, Δu)")
    if VB:
        binned_plot(ax[3], np.concatenate(VB), R, "battery voltage (battery_sag)")
    fig.tight_layout()
    fig.savefig(out / "diagnostics.png", dpi=90)
    plt.close(fig)

    _candidate_plot(out, sel)


def _candidate_plot(out: Path, sel) -> None:
    """Held-out gain of every candidate, per round."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.5))
    rounds = [rd for rd in sel.rounds if "candidates" in rd]  # not the backward pruning record
    width = 0.8 / max(1, len(rounds))
    names = [c["name"] for c in rounds[0]["candidates"]] if rounds else []
    for i, rd in enumerate(rounds):
        gains = {c["name"]: c["heldout_gain"] for c in rd["candidates"]}
        ax.bar(np.arange(len(names)) + i * width, [gains.get(n, 0.0) for n in names], width, label=f"round {rd['round']}")
    ax.set_xticks(np.arange(len(names)))
    ax.set_xticklabels(names, rotation=45, ha="right", fontsize=7)
    ax.set_ylabel("held-out gain")
    ax.axhline(0, color="k", lw=0.5)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "candidates.png", dpi=90)
    plt.close(fig)

