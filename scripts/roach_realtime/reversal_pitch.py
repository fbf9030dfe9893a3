"""Does a trained roach model predict the pitch-over that a leg reversal at speed causes?

usage: PYTHONPATH=<checkout> python scripts/roach_realtime/reversal_pitch.py MODEL.pt [...]

On the lockstep sim: 2 s at 15 rev/s on both sides, then 4 periods of -15 rev/s (reverse) or 0
(stop); prints the true pitch (deg) over those 4 periods and each model's open-loop prediction
from the state before them (docs/velociroach.md, "Three emulated runs").
"""

import sys

import numpy as np
import torch

from hilstack.drivers.registry import make_backend
from hilstack.learning.frames import load_dynamics

torch.set_num_threads(1)
sim = make_backend("velociroach", "sim")
sim.configure()
sim.activate()
act = sim.spec.action


def pitch_deg(s):
    return np.degrees(np.arctan2(s[..., 9], s[..., 8]))


def trajectory(second, n1=20, n2=4):
    sim.reset(yaw=0.0)
    states, actions = [], []
    for cmd, n in (((15.0, 15.0), n1), (second, n2)):
        for _ in range(n):
            sim.write(np.array(cmd))
            sim.tick()
            states.append(sim.read().state.copy())
            actions.append(act.normalize(np.array(cmd)))
    return np.array(states, np.float32), np.array(actions, np.float32)


for path in sys.argv[1:]:
    model = load_dynamics(path)
    for name, second in (("reverse", (-15.0, -15.0)), ("stop", (0.0, 0.0))):
        s, a = trajectory(second)
        x, pred = torch.as_tensor(s[19:20]), []
        with torch.inference_mode():
            for h in range(4):
                x = model.predict(x, torch.as_tensor(a[20 + h:21 + h])).mean(0)
                pred.append(float(pitch_deg(x.numpy())[0]))
        print(f"{path} {name}: true pitch {pitch_deg(s[20:24]).round(0)}, predicted {np.round(pred, 0)}")
