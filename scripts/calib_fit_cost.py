"""CPU seconds of 24 refined `axis` fits (4 effect sets x 6 bootstrap weightings of a 12-episode synthetic
recording), twice; with `axis.USE_COMPILED` (round 6) also through the numpy replay. Prints the CPU
seconds and the sum of the fitted gains a (equal on two commits = the same fits).

    PYTHONPATH=. nice -n 10 python scripts/calib_fit_cost.py LABEL    # run on two checkouts side by side
"""

import json
import sys
import time

import numpy as np

from hilstack.calibration import axis
from hilstack.calibration.synthetic import SynthConfig, generate

preps = axis.prepare(generate(SynthConfig(n_episodes=12, seed=0, effects={"coulomb_friction": {}, "delay": {}})))
rng = np.random.default_rng(0)
W = [rng.poisson(1.0, len(preps)).astype(float) for _ in range(6)]
modes = [("as_is", True)] + ([("numpy_replay", False)] if hasattr(axis, "USE_COMPILED") else [])
axis.fit_axis(preps, ["coulomb_friction"], weights=W[0])  # warm-up (numba compile/cache load)
res = {}
for _rep in range(2):
    for label, comp in modes:
        if hasattr(axis, "USE_COMPILED"):
            axis.USE_COMPILED = comp
        for p in preps:
            p.stats_cache.clear()
            getattr(p, "feature_cache", {}).clear()
        c0 = time.process_time()
        out = []
        for w in W:
            for eff in (["coulomb_friction"], ["coulomb_friction", "delay"], ["delay", "backlash"], ["gravity_load", "coulomb_friction"]):
                prm = axis.fit_axis(preps, eff, weights=w)
                out.append(prm.coef["a"])
        res.setdefault(label, []).append(round(time.process_time() - c0, 2))
        res[label + "_a_sum"] = float(np.sum(out))
print(sys.argv[1] if len(sys.argv) > 1 else "run", json.dumps(res))
