"""Does the run's model see a tip coming? 4-step open-loop tilt predictions on an evaluation recording.

usage: PYTHONPATH=<checkout> python scripts/roach_realtime/tilt_prediction.py OUT [H]

OUT: a `hil demo --rig roach_emulated` output (OUT/model.pt, OUT/recordings/900-eval.mcap). For
every state of every episode, the model's open-loop prediction over the next H (4, the
planner's horizon) recorded actions; the largest |roll| or |pitch| it predicts beside the one
that happened, beside the persistence baseline (the tilt of the state the window starts
from). Prints, over all steps where the true H-step tilt went past 20° (the tipping
term's threshold), how often the prediction went past it too, the error of the predicted
peak tilt, and for each episode that ended tipped (cos roll or pitch < 0.7) the predicted and
true peak tilt from the H states before the end (docs/velociroach.md, "Three emulated runs
with the sample count refitted").
"""

import sys

import numpy as np
import torch

from hilstack.drivers.velociroach.config import STATE_NAMES
from hilstack.learning.frames import load_dynamics
from hilstack.learning.recordings import episodes_from_mcap

torch.set_num_threads(1)
out = sys.argv[1]
H = int(sys.argv[2]) if len(sys.argv) > 2 else 4
model = load_dynamics(f"{out}/model.pt")
ir, ip = STATE_NAMES.index("cos_roll"), STATE_NAMES.index("cos_pitch")


def tilt_deg(s):
    """max(|roll|, |pitch|) in degrees of states [..., S]."""
    roll = np.arctan2(s[..., ir + 1], s[..., ir])
    pitch = np.arctan2(s[..., ip + 1], s[..., ip])
    return np.degrees(np.maximum(np.abs(roll), np.abs(pitch)))


true_pk, pred_pk, now_pk, tipped = [], [], [], []
for e in episodes_from_mcap(f"{out}/recordings/900-eval.mcap", "roach"):
    S, A = np.asarray(e.states, np.float32), np.asarray(e.actions, np.float32)
    T = len(A)
    if T < H:
        continue
    starts = np.arange(T - H + 1)
    x = torch.as_tensor(S[starts])
    preds = []
    with torch.inference_mode():
        for k in range(H):
            x = model.predict(x, torch.as_tensor(A[starts + k])).mean(0)
            preds.append(x.numpy())
    pk_pred = tilt_deg(np.stack(preds, 1)).max(1)
    pk_true = np.stack([tilt_deg(S[starts + k + 1]) for k in range(H)], 1).max(1)
    true_pk.append(pk_true)
    pred_pk.append(pk_pred)
    now_pk.append(tilt_deg(S[starts]))  # the persistence baseline: the tilt stays as it is now
    end = S[-1]
    if min(end[ir], end[ip]) < 0.7:
        tipped.append((len(S), pk_pred[-1], pk_true[-1], pk_pred[max(0, T - 2 * H):T - H + 1].max()))
t, p, z = np.concatenate(true_pk), np.concatenate(pred_pk), np.concatenate(now_pk)
over = t > 20.0
print(f"{out}: {len(t)} {H}-step windows; true peak tilt > 20 deg in {over.sum()}, predicted > 20 deg in "
      f"{(p[over] > 20).sum()} of those ({(p[~over] > 20).sum()} false alarms in {(~over).sum()}); "
      f"peak tilt error (pred - true) where true > 20: median {np.median(p[over] - t[over]):.1f}, "
      f"p10/p90 {np.percentile(p[over] - t[over], 10):.1f}/{np.percentile(p[over] - t[over], 90):.1f} deg; "
      f"persistence (today's tilt): > 20 deg in {(z[over] > 20).sum()} of those, median error {np.median(z[over] - t[over]):.1f}")
for n, last_pred, last_true, earlier in tipped:
    print(f"  tipped episode ({n} states): last window predicted {last_pred:.0f} deg, true {last_true:.0f}; "
          f"the {H} windows before it predicted at most {earlier:.0f} deg")
