"""Which model lever makes the roach's model see a tip coming? Offline, on recorded runs.

usage: PYTHONPATH=<checkout> python scripts/roach_realtime/tilt_levers.py OUT [VARIANT ...]

OUT: a `hil demo --rig roach_emulated --quick` output. Each variant's model is trained as the
demo's loop trains it (the quick preset: 40 epochs on OUT/recordings/000-random.mcap, then 10
more with the on-policy episodes of 001-mpc.mcap added; the same split rule), seeded with the
run's seed, and scored on the run's evaluation recording (900-eval.mcap, both controllers'
episodes) the way tilt_prediction.py scores the run's own model: from every state, the 4-step
open-loop prediction through the recorded actions; over the windows whose true peak tilt
(max |roll|, |pitch|) passed 20°, the share the model also predicted past 20° (ensembles: the
member mean, and any member), the false alarms, and the median error of the predicted peak.
Variants (docs/velociroach.md, "A model that predicts the tilt"):
  current        the demo's model (one-step loss, all channels weighted 1)
  tiltw5/tiltw20 tilt channels (cos/sin roll, pitch; wx, wy) weighted 5 / 20 in the loss
  h4             4-step open-loop loss after the one-step fit (train_horizon=4)
  h4_tiltw5      both
  ens5           an ensemble of 5 (bootstrap)
  more_data      the current model, then 10 more epochs with the baseline tuning episodes added
                 (800-tune-baseline, both speeds; 36 episodes in seed 0: more data at speed)
"""

import sys
import time

import numpy as np
import torch

from hilstack.drivers.velociroach.config import STATE_NAMES
from hilstack.learning.mbrl import MbrlConfig, fit_episodes, make_model
from hilstack.learning.recordings import episodes_from_mcap

torch.set_num_threads(1)
VARIANTS = {
    "current": {},
    "tiltw5": dict(tilt_loss_weight=5.0),
    "tiltw20": dict(tilt_loss_weight=20.0),
    "h4": dict(train_horizon=4),
    "h4_tiltw5": dict(train_horizon=4, tilt_loss_weight=5.0),
    "ens5": dict(ensemble=5),
    "more_data": {},
}
out = sys.argv[1]
names = sys.argv[2:] or list(VARIANTS)
H, THR = 4, 20.0
rep = __import__("json").load(open(f"{out}/report.json"))
seed = int(rep["config"]["seed"])
rnd = episodes_from_mcap(f"{out}/recordings/000-random.mcap", "roach")
onp = episodes_from_mcap(f"{out}/recordings/001-mpc.mcap", "roach")
ev = episodes_from_mcap(f"{out}/recordings/900-eval.mcap", "roach")
state_names = list(STATE_NAMES)
action_names = ["leg_vel_l", "leg_vel_r"]
ir, ip = state_names.index("cos_roll"), state_names.index("cos_pitch")


def tilt_deg(s):
    roll = np.arctan2(s[..., ir + 1], s[..., ir])
    pitch = np.arctan2(s[..., ip + 1], s[..., ip])
    return np.degrees(np.maximum(np.abs(roll), np.abs(pitch)))


def score(model):
    tp, pm, pa = [], [], []
    for e in ev:
        S, A = e.states, e.actions
        T = len(A)
        if T < H:
            continue
        st = np.arange(T - H + 1)
        x = torch.as_tensor(S[st])
        preds = []
        with torch.inference_mode():
            for k in range(H):
                x = model.predict(x, torch.as_tensor(A[st + k]))  # [E, P, S]
                preds.append(x.numpy())
                x = x.mean(0)
        P = np.stack(preds, 2)  # [E, P, H, S]
        tp.append(np.stack([tilt_deg(S[st + k + 1]) for k in range(H)], 1).max(1))
        pm.append(tilt_deg(P.mean(0)).max(1))
        pa.append(tilt_deg(P).max(2).max(0))
    t, p, a = map(np.concatenate, (tp, pm, pa))
    over = t > THR
    return dict(windows=len(t), over=int(over.sum()), hit=int((p[over] > THR).sum()),
                hit_any=int((a[over] > THR).sum()), false=int((p[~over] > THR).sum()),
                false_any=int((a[~over] > THR).sum()),
                err_med=float(np.median(p[over] - t[over])), err_p10=float(np.percentile(p[over] - t[over], 10)),
                err_p90=float(np.percentile(p[over] - t[over], 90)))


for name in names:
    t0 = time.monotonic()
    cfg = MbrlConfig.from_preset("quick", seed=seed, progress=False, **VARIANTS[name])
    torch.manual_seed(seed)
    model = make_model(cfg, state_names, action_names)
    rng, assigned = np.random.default_rng([seed, 1]), {}
    fit_episodes(model, list(rnd), cfg.epochs, cfg.batch_size, cfg.val_fraction, rng, assigned, horizon=H)
    data = list(rnd) + list(onp)
    fit_episodes(model, data, cfg.retrain_epochs, cfg.batch_size, cfg.val_fraction, rng, assigned, horizon=H)
    if name == "more_data":
        tune = episodes_from_mcap(f"{out}/recordings/800-tune-baseline.mcap", "roach")
        fit_episodes(model, data + list(tune), cfg.retrain_epochs, cfg.batch_size, cfg.val_fraction, rng,
                     assigned, horizon=H)
    r = score(model)
    print(f"{out} seed {seed} {name:10s}: true>20 in {r['over']}/{r['windows']}; predicted>20 (mean) {r['hit']} "
          f"(any member {r['hit_any']}); false alarms {r['false']} ({r['false_any']}); peak error median "
          f"{r['err_med']:.1f} p10/p90 {r['err_p10']:.1f}/{r['err_p90']:.1f} deg; train {time.monotonic() - t0:.0f} s",
          flush=True)
