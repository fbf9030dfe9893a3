"""One-step error of a dynamics checkpoint on recordings (world frame, some channels).

usage: onestep.py MODEL.pt RECORDING.mcap [...]
"""

import sys

import numpy as np
import torch

from hilstack.drivers.velociroach.config import STATE_NAMES
from hilstack.learning.frames import load_dynamics
from hilstack.learning.recordings import episodes_from_mcap

torch.set_num_threads(1)
model = load_dynamics(sys.argv[1])
channels = ["x", "y", "cos_yaw", "sin_yaw", "crank_vel_l", "crank_vel_r"]
idx = [STATE_NAMES.index(c) for c in channels]
for path in sys.argv[2:]:
    errs = []
    for e in episodes_from_mcap(path, "roach"):
        with torch.inference_mode():
            p = model.predict(torch.as_tensor(e.states[:-1], dtype=torch.float32),
                              torch.as_tensor(e.actions, dtype=torch.float32)).mean(0).numpy()
        errs.append(np.abs(p - e.states[1:])[:, idx])
    err = np.concatenate(errs)
    print(path, len(err), "transitions; mean |error|:", ", ".join(f"{c} {v:.3f}" for c, v in zip(channels, err.mean(0),
                                                                                                    strict=True)))
