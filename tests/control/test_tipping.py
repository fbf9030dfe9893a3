"""The path cost's tipping term and the baseline's tilt limit (issue 29)."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from hilstack.control.baselines import DifferentialDriveController
from hilstack.control.costs import PathCost, evaluate_path_following
from hilstack.control.paths import make_path
from hilstack.control.planners import CEM
from hilstack.control.policies import MpcPolicy
from hilstack.learning.mbrl import MbrlConfig, task_cost

NAMES = [
    "x", "y", "z", "vx", "vy", "vz", "cos_roll", "sin_roll", "cos_pitch", "sin_pitch",
    "cos_yaw", "sin_yaw", "wx", "wy", "wz", "cos_left_crank", "sin_left_crank",
    "cos_right_crank", "sin_right_crank", "left_crank_vel", "right_crank_vel",
    "left_bemf", "right_bemf", "vbat",
]
IDX = {n: i for i, n in enumerate(NAMES)}


def state(x=0.0, y=0.0, yaw=0.0, roll=0.0, pitch=0.0):
    s = torch.zeros(24)
    s[IDX["x"]], s[IDX["y"]] = x, y
    s[IDX["cos_yaw"]], s[IDX["sin_yaw"]] = math.cos(yaw), math.sin(yaw)
    s[IDX["cos_roll"]], s[IDX["sin_roll"]] = math.cos(roll), math.sin(roll)
    s[IDX["cos_pitch"]], s[IDX["sin_pitch"]] = math.cos(pitch), math.sin(pitch)
    return s


def tippy_unicycle(s, a, dt=0.1, v_max=1.2, w_max=12.0, roll_per_accel=0.25):
    """A unicycle that rolls outward in proportion to its lateral acceleration v·ω (rad per m/s²):
    one side at full speed and the other stopped rolls 0.25·0.6·6 = 0.9 rad (52°), like the sim roach
    (51° spinning in place, docs/velociroach.md)."""
    left, right = a[..., 0], a[..., 1]
    yaw = torch.atan2(s[..., IDX["sin_yaw"]], s[..., IDX["cos_yaw"]])
    v = v_max * 0.5 * (left + right)
    w = w_max * 0.5 * (right - left)
    out = s.clone()
    out[..., IDX["x"]] = s[..., IDX["x"]] + dt * v * torch.cos(yaw)
    out[..., IDX["y"]] = s[..., IDX["y"]] + dt * v * torch.sin(yaw)
    out[..., IDX["cos_yaw"]], out[..., IDX["sin_yaw"]] = torch.cos(yaw + dt * w), torch.sin(yaw + dt * w)
    roll = roll_per_accel * v * w
    out[..., IDX["cos_roll"]], out[..., IDX["sin_roll"]] = torch.cos(roll), torch.sin(roll)
    return out


def rollout(actions, s0):
    out = [s0]
    for a in actions:
        out.append(tippy_unicycle(out[-1], torch.as_tensor(a, dtype=torch.float32)))
    return torch.stack(out)


def test_rolled_state_costs_more_beyond_the_threshold_only():
    wp = np.array([[0.0, 0.0], [2.0, 0.0]])
    tip = PathCost(wp, NAMES, f_tip=50.0, tip_threshold_rad=math.radians(20))
    plain = PathCost(wp, NAMES)
    s0 = state()

    def traj(roll=0.0, pitch=0.0):
        return torch.stack([s0, state(0.1, 0.0, 0.0, roll, pitch)])

    # below the threshold: the same as the thesis' cost
    assert float(tip(traj(math.radians(15)))) == pytest.approx(float(plain(traj(math.radians(15)))))
    # 40° roll (or pitch, either sign) costs f_tip · 20° more
    for r, p in ((40, 0), (-40, 0), (0, 40)):
        extra = float(tip(traj(math.radians(r), math.radians(p)))) - float(plain(traj(math.radians(r), math.radians(p))))
        assert extra == pytest.approx(50.0 * math.radians(20), rel=1e-4)
    # the evaluation's thesis cost (f_tip = 0) does not look at roll at all
    assert float(plain(traj(math.radians(60)))) == pytest.approx(float(plain(traj())))


def test_hard_turn_at_speed_costs_more_than_a_slow_turn_only_with_the_term():
    """On a right turn a full-speed pivot makes more progress (cheaper under the thesis' cost)
    but rolls ~49°; slowing into the turn rolls < 20°. The tipping term reverses the order."""
    wp = np.array([[0.0, 0.0], [0.3, 0.0], [0.3, -1.0]])
    s0 = state(0.25, 0.0, 0.0)  # just before the corner
    hard = rollout([[1.0, -0.3]] * 4, s0)  # full speed, hard right
    slow = rollout([[0.4, 0.15]] * 4, s0)  # slower, gentler
    assert float(torch.atan2(hard[:, IDX["sin_roll"]], hard[:, IDX["cos_roll"]]).abs().max()) > math.radians(30)
    assert float(torch.atan2(slow[:, IDX["sin_roll"]], slow[:, IDX["cos_roll"]]).abs().max()) < math.radians(20)
    plain = PathCost(wp, NAMES)
    tip = PathCost(wp, NAMES, f_tip=50.0, tip_threshold_rad=math.radians(20))
    assert float(plain(hard)) < float(plain(slow))
    assert float(tip(hard)) > float(tip(slow))


def test_mpc_with_the_term_keeps_roll_below_the_threshold_on_a_turn():
    wp = make_path("right")
    th = 10.0

    def run(f_tip):
        cost = PathCost(wp, NAMES, f_tip=f_tip, tip_threshold_rad=math.radians(th))
        pol = MpcPolicy(SimpleNamespace(predict=tippy_unicycle),
                        CEM(-1.0, 1.0, horizon=4, samples=300, action_dim=2, iterations=5, seed=0), cost)
        s, rolls, states = state(), [], [state()]
        for _ in range(40):
            s = tippy_unicycle(s, torch.as_tensor(pol(s.numpy()), dtype=torch.float32))
            states.append(s)
            rolls.append(abs(math.degrees(math.atan2(float(s[IDX["sin_roll"]]), float(s[IDX["cos_roll"]])))))
        m = evaluate_path_following(torch.stack(states).numpy(), PathCost(wp, NAMES))
        return max(rolls), m["progress_m"]

    roll_plain, progress_plain = run(0.0)
    roll_tip, progress_tip = run(50.0)
    assert roll_plain > th + 5.0  # the thesis' cost rolls well past the threshold on this robot
    assert roll_tip < th  # the term keeps the executed roll within it
    assert progress_tip > 0.5  # and the robot still drives along the path (slower: progress_plain)
    assert progress_tip < progress_plain


def test_baseline_stops_turning_harder_as_it_rolls_past_the_threshold():
    wp = np.array([[0.0, 0.0], [2.0, 0.0]])
    th = math.radians(20)
    limited = DifferentialDriveController(wp, NAMES, tip_threshold_rad=th)
    free = DifferentialDriveController(wp, NAMES)
    off = state(0.0, 0.3, 0.0).numpy()  # left of the path: both steer right
    a_free = free(off)
    assert a_free[0] > a_free[1]
    np.testing.assert_allclose(limited(off), a_free)  # upright: identical
    rolled = state(0.0, 0.3, 0.0, roll=math.radians(30)).numpy()  # half-way to 2θ: half the turn
    a = limited(rolled)
    assert a[0] - a[1] == pytest.approx(0.5 * (a_free[0] - a_free[1]), rel=1e-4)
    a = limited(state(0.0, 0.3, 0.0, pitch=math.radians(45)).numpy())  # beyond 2θ: straight
    assert a[0] == pytest.approx(a[1])


def test_config_default_and_bad_values():
    cfg = MbrlConfig()
    assert cfg.tip_weight == 50.0 and cfg.tip_threshold_deg == 20.0
    c = task_cost(cfg, np.array([[0.0, 0.0], [1.0, 0.0]]), NAMES)
    assert c.f_tip == 50.0 and c.tip_threshold_rad == pytest.approx(math.radians(20))
    # a robot without roll/pitch channels gets the thesis' cost
    assert task_cost(cfg, np.array([[0.0, 0.0], [1.0, 0.0]]), ["x", "y", "cos_yaw", "sin_yaw"]).f_tip == 0.0
    with pytest.raises(ValueError, match="tip_weight"):
        MbrlConfig(tip_weight=float("nan"))
    with pytest.raises(ValueError, match="tip_threshold_deg"):
        MbrlConfig(tip_threshold_deg=95.0)
    with pytest.raises(ValueError, match="roll and pitch"):
        PathCost(np.array([[0.0, 0.0], [1.0, 0.0]]), ["x", "y", "cos_yaw", "sin_yaw"], f_tip=1.0)
    with pytest.raises(ValueError, match="tip_threshold_rad"):
        DifferentialDriveController(np.array([[0.0, 0.0], [1.0, 0.0]]), NAMES, tip_threshold_rad=2.0)


def test_report_max_tilt_degrees():
    from hilstack.learning.mbrl import max_tilt_deg

    s = torch.stack([state(), state(roll=math.radians(-33)), state(pitch=math.radians(12))]).numpy()
    assert max_tilt_deg(s, NAMES) == pytest.approx(33.0, abs=1e-3)
    assert math.isnan(max_tilt_deg(s[:, :4], ["x", "y", "z", "vx"]))
