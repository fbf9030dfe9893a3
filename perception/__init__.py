"""Perception: stereo geometry and the Baoding-ball trackers (classical and learned).

Depends on numpy, OpenCV and torch only (never on sim_backends): the real camera driver
and the sim backends both use it. Rendering training data (:mod:`hilstack.tools.train_keypoints`) is
the one module that needs the MuJoCo hand scene.
"""
