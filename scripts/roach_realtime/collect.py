"""Record N random rollouts on a rig through MbrlRun (the demo's own data collection).

usage: collect.py RIG N OUT_DIR
"""

import sys
import time
from pathlib import Path

import torch

from hilstack.configs.schema import BusConfig
from hilstack.learning.mbrl import MbrlConfig, MbrlRun
from tests.helpers import free_port

torch.set_num_threads(1)
rig, n, out = sys.argv[1], int(sys.argv[2]), Path(sys.argv[3])
run = MbrlRun(MbrlConfig.from_preset("quick", rig=rig, random_rollouts=n), out, BusConfig(endpoint=f"tcp/127.0.0.1:{free_port()}"))
t0 = time.monotonic()
with run.session():
    p = run.collect_random(n, "000-random")
print("recorded", p, f"{time.monotonic() - t0:.0f} s")
