"""How predictable is the roach's peak tilt 4 steps ahead at all? A direct predictor, offline.

usage: PYTHONPATH=<checkout> python scripts/roach_realtime/tilt_ceiling.py OUT

A small MLP (2x128, Adam 1e-3, 300 epochs) maps (the state in its own body frame, the next 4
recorded actions) straight to the peak |roll| or |pitch| of the next 4 states, trained on the
data the demo's model saw (000-random + 001-mpc), scored on 900-eval as tilt_prediction.py
scores the dynamics model: a regressor (MSE on the peak in degrees) and a classifier (logistic
loss on "peak > 20°"). If these, trained for exactly this quantity, do not flag the windows
that tipped past 20°, no dynamics model trained on these data will either. Also prints how
well the dynamics model's signed roll matches the truth 1..4 steps ahead (correlation), the
sign being what a mean-squared-error model must get right to predict |roll|.
"""

import json
import sys

import numpy as np
import torch

from hilstack.drivers.velociroach.config import STATE_NAMES
from hilstack.learning.frames import PlanarFrame, load_dynamics
from hilstack.learning.recordings import episodes_from_mcap

torch.set_num_threads(1)
out = sys.argv[1]
H, THR = 4, 20.0
seed = int(json.load(open(f"{out}/report.json"))["config"]["seed"])
names = list(STATE_NAMES)
ir, ip = names.index("cos_roll"), names.index("cos_pitch")
frame = PlanarFrame(names)


def tilt_deg(s):
    roll = np.arctan2(s[..., ir + 1], s[..., ir])
    pitch = np.arctan2(s[..., ip + 1], s[..., ip])
    return np.degrees(np.maximum(np.abs(roll), np.abs(pitch)))


def windows(eps):
    X, Y = [], []
    for e in eps:
        S, A = e.states.astype(np.float64), e.actions
        T = len(A)
        if T < H:
            continue
        st = np.arange(T - H + 1)
        body = frame.to_body(S[st], S[st])
        X.append(np.concatenate([body, A[st[:, None] + np.arange(H)].reshape(len(st), -1)], 1))
        Y.append(np.stack([tilt_deg(S[st + k + 1]) for k in range(H)], 1).max(1))
    return np.concatenate(X).astype(np.float32), np.concatenate(Y).astype(np.float32)


train = episodes_from_mcap(f"{out}/recordings/000-random.mcap", "roach") + \
    episodes_from_mcap(f"{out}/recordings/001-mpc.mcap", "roach")
ev = episodes_from_mcap(f"{out}/recordings/900-eval.mcap", "roach")
Xtr, ytr = windows(train)
Xev, yev = windows(ev)
mu, sd = Xtr.mean(0), Xtr.std(0) + 1e-6
xt, xe = torch.as_tensor((Xtr - mu) / sd), torch.as_tensor((Xev - mu) / sd)


def mlp():
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(xt.shape[1], 128), torch.nn.ReLU(), torch.nn.Linear(128, 128),
                               torch.nn.ReLU(), torch.nn.Linear(128, 1))


def train_net(net, target, lossf, epochs=300):
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    g = torch.Generator().manual_seed(seed)
    for _ in range(epochs):
        for idx in torch.randperm(len(xt), generator=g).split(256):
            loss = lossf(net(xt[idx]).squeeze(-1), target[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
    with torch.no_grad():
        return net(xe).squeeze(-1).numpy()


over = yev > THR
reg = train_net(mlp(), torch.as_tensor(ytr), torch.nn.functional.mse_loss)
cls = 1 / (1 + np.exp(-train_net(mlp(), torch.as_tensor((ytr > THR).astype(np.float32)),
                                 torch.nn.functional.binary_cross_entropy_with_logits)))
# AUC of the classifier (rank statistic)
r = np.argsort(np.argsort(cls))
auc = (r[over].mean() - (over.sum() - 1) / 2) / (~over).sum()
print(f"{out} seed {seed}: train windows {len(ytr)} (peak > 20 in {(ytr > THR).sum()}), eval {len(yev)} "
      f"(> 20 in {over.sum()})")
print(f"  direct regressor: predicted > 20 in {(reg[over] > THR).sum()} of {over.sum()} "
      f"({(reg[~over] > THR).sum()} false alarms); peak error median {np.median(reg[over] - yev[over]):.1f} deg")
for p in (0.5, 0.2):
    print(f"  direct classifier p > {p}: {(cls[over] > p).sum()} of {over.sum()} ({(cls[~over] > p).sum()} false alarms "
          f"in {(~over).sum()})")
print(f"  classifier AUC {auc:.2f} (0.5: chance)")
model = load_dynamics(f"{out}/model.pt")
cors = []
for k in range(1, H + 1):
    pr, tr = [], []
    for e in ev:
        S, A = e.states, e.actions
        T = len(A)
        if T < H:
            continue
        st = np.arange(T - H + 1)
        x = torch.as_tensor(S[st])
        with torch.inference_mode():
            for j in range(k):
                x = model.predict(x, torch.as_tensor(A[st + j])).mean(0)
        pr.append(np.degrees(np.arctan2(x[:, ir + 1].numpy(), x[:, ir].numpy())))
        tr.append(np.degrees(np.arctan2(S[st + k, ir + 1], S[st + k, ir])))
    pr, tr = np.concatenate(pr), np.concatenate(tr)
    cors.append(f"{k}: r={np.corrcoef(pr, tr)[0, 1]:.2f} (std pred {pr.std():.1f} / true {tr.std():.1f} deg)")
print("  the run's model, signed roll k steps ahead vs truth: " + "; ".join(cors))
