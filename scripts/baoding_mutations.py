"""Issue 30's third done-when: break ``init_mean``, the action filter and the ball velocities on
purpose, one at a time, in a copy of the tree, and name the Baoding tests that fail (docs/baoding.md,
"Done-when 3"). A break no test notices prints no FAILED line under it.

    python scripts/baoding_mutations.py [INDEX ...]      # all breaks, or the ones numbered

Each break is an exact text replacement (it must match once); the copy is made from ``git ls-files``
in a temporary directory, so the checkout is never edited.
"""
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
MUTS = [
 ("init_mean: the planner ignores it (middle of the bounds)", "control/planners.py",
  'init = (self.action_low + self.action_high) / 2 if self._init_mean is None else _vec(\n            self._init_mean, self.action_dim, "init_mean")',
  'init = (self.action_low + self.action_high) / 2'),
 ("init_mean: the run gives 'mid' whatever the config", "learning/baoding.py",
  'if self.bcfg.init_mean == "hold":', 'if False:'),
 ("init_mean: the filter's anchor is not the first mean after a reset", "control/planners.py",
  'self.previous = self.mean[0].clone()', 'self.previous = torch.zeros_like(self.mean[0])'),
 ("init_mean: reset keeps the last plan's mean", "control/planners.py",
  '        self.mean = init.expand(self.horizon, -1).clone()',
  '        self.mean = init.expand(self.horizon, -1).clone() if getattr(self, "mean", None) is None else self.mean'),
 ("action filter: 'actions' filters the noise", "control/planners.py",
  'if self.filter == "actions":  # smooth', 'if False:  # smooth'),
 ("action filter: anchored at zero, not the action executed last", "control/planners.py",
  'prev = self.previous.expand(N, A)\n', 'prev = torch.zeros(N, A)\n'),
 ("action filter: beta and 1-beta swapped", "control/planners.py",
  'prev = b * (mean[t] + u[:, t]) + (1.0 - b) * prev', 'prev = (1.0 - b) * (mean[t] + u[:, t]) + b * prev'),
 ("action filter: a plan does not update the anchor", "control/planners.py",
  '        self.previous = self._step(plan, k)\n        self.mean = self._after(plan, k)', '        self.mean = self._after(plan, k)'),
 ("ball velocities: zero in recorded episodes", "learning/baoding.py",
  'vel[1:] = (balls[1:] - balls[:-1]) / self.period_s', 'pass'),
 ("ball velocities: zero while planning (per-step call)", "learning/baoding.py",
  'vel = np.zeros(6) if self._prev is None else (balls - self._prev) / self.period_s', 'vel = np.zeros(6)'),
 ("ball velocities: not divided by the period while planning", "learning/baoding.py",
  'vel = np.zeros(6) if self._prev is None else (balls - self._prev) / self.period_s', 'vel = np.zeros(6) if self._prev is None else (balls - self._prev)'),
 ("ball velocities: previous balls not updated (velocity from the episode's first state)", "learning/baoding.py",
  '        self._prev = balls.copy()\n', '        self._prev = balls.copy() if self._prev is None else self._prev\n'),
 ("ball velocities: reset() does not forget the last episode's balls", "learning/baoding.py",
  '    def reset(self) -> None:\n        self._prev = None', '    def reset(self) -> None:\n        pass'),
 ("ball velocities: the policy's reset does not reset the features", "learning/baoding.py",
  '        self.mpc.reset()\n        self.features.reset()', '        self.mpc.reset()'),
 ("ball velocities: swap_balls swaps the positions only", "learning/baoding.py",
  "st[:, i0:i0 + 6], st[:, i1:i1 + 6] = ep.states[:, i1:i1 + 6], ep.states[:, i0:i0 + 6]",
  "st[:, i0:i0 + 3], st[:, i1:i1 + 3] = ep.states[:, i1:i1 + 3], ep.states[:, i0:i0 + 3]"),
]
TESTS = ["tests/shadow_hand/test_pddm_planner.py", "tests/shadow_hand/test_baoding_fidelity.py",
         "tests/shadow_hand/test_demo_baoding.py", "tests/shadow_hand/test_baoding_diagnose.py"]
SLOW = "not resumes_after and not tiny_end_to_end and not thesis_scale_cost and not drop_ends_the_episode"


def main(only: list[str]) -> None:
    root = Path(tempfile.mkdtemp(prefix="baoding-mut-"))
    files = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout.split(b"\0")
    for f in filter(None, files):
        dst = root / f.decode()
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / f.decode(), dst)
    try:
        run(root, only)
    finally:
        shutil.rmtree(root, ignore_errors=True)


def run(root: Path, only: list[str]) -> None:
    home = Path(tempfile.mkdtemp(prefix="baoding-mut-home-"))
    env = {**os.environ, "PYTHONPATH": str(root), "HOME": str(home)}
    for i, (name, f, old, new) in enumerate(MUTS):
        if only and str(i) not in only:
            continue
        p = root / f
        src = p.read_text()
        if src.count(old) != 1:
            sys.exit(f"[{i}] {name}: the text to break is not in {f} exactly once (the code changed): update MUTS")
        p.write_text(src.replace(old, new))
        try:
            r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:randomly", "-rf", "-k", SLOW, *TESTS],
                               cwd=root, capture_output=True, text=True, env=env)
            failed = sorted(set(re.findall(r"FAILED (\S+?)(?: - |$)", r.stdout, re.M)))
            tail = r.stdout.strip().splitlines()[-1] if r.stdout.strip() else r.stderr[-200:]
            print(f"[{i}] {name}: {tail}")
            for t in failed:
                print(f"      FAILED {t}")
        finally:
            p.write_text(src)
        sys.stdout.flush()
    shutil.rmtree(home, ignore_errors=True)


if __name__ == "__main__":
    main(sys.argv[1:])
