"""MELD: meta-RL from images as latent state estimation (thesis ch. 7; docs/meld.md).

model.py (latent variable model, ELBO of Eq. 7.4, online belief filter), sac.py (SAC on a
feature vector), replay.py (per-task episode buffers), agents.py (MELD, SLAC, SAC on a history),
train.py (Algorithms 7 and 8), toy.py (a point reacher drawn in tiny images, for tests),
node.py (a policy driving an arm and its task-reset mechanism over the bus), diagnose.py (SAC
on the true state and goal: the lower bound MELD is measured against).
The robots' tasks (WidowX and the task-reset mechanism, the Sawyer reacher) are wired in
tools/meld_tasks.py and tools/demo_meld.py.
"""
