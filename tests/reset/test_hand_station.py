"""The hand's reset station in the MuJoCo scene (ramp, pick-up spot, reset arm) and the
arm's kinematics: fast checks without the bus."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
import yaml

from hilstack.drivers.base import LinkError
from hilstack.drivers.reset_arm.config import ResetArmParams
from hilstack.drivers.shadow_hand.config import ShadowHandParams, hold_pose_action
from hilstack.sim_backends.reset_arm.backend import ResetArmSim
from hilstack.sim_backends.reset_arm.ik import READY_Q_RAD, ArmIK, down_frame
from hilstack.sim_backends.shadow_hand.backend import ShadowHandSim
from hilstack.sim_backends.shadow_hand.model import BALL_RADIUS_M

RIG = Path(__file__).resolve().parents[2] / "configs" / "rigs" / "hand_sim_arm.yaml"


def hand(station: bool, **sim) -> ShadowHandSim:
    h = ShadowHandSim(ShadowHandParams(sim={"reset_station": station, **sim}))
    h.configure()
    h.activate()
    return h


def run_held(h: ShadowHandSim, periods: int) -> None:
    for _ in range(periods):
        h.write(hold_pose_action())
        h.tick()


def test_the_station_leaves_the_baoding_physics_unchanged():
    plain, station = hand(False), hand(True, world="station-physics")
    try:
        run_held(plain, 20)
        run_held(station, 20)
        np.testing.assert_array_equal(plain.balls_m(), station.balls_m())
        for a, b in zip(plain.joint_state(), station.joint_state(), strict=True):
            np.testing.assert_array_equal(a, b)
        assert not station.task.dropped(station.balls_m())
    finally:
        plain.cleanup()
        station.cleanup()


def test_dropped_balls_roll_down_the_ramp_to_the_pickup_spot():
    h = hand(True, world="station-ramp")
    try:
        # both thrown over the fingertips (the balls start where they rest in the palm, nestled)
        for v, d in zip(((0.5, 0.3, 0.5), (0.6, 0.3, 0.5)), h.hand.ball_dof_adr, strict=True):
            h.data.qvel[d:d + 3] = v
        run_held(h, 25)
        g = h.hand.station
        spots = np.stack([g.spot_m(BALL_RADIUS_M, 0), g.spot_m(BALL_RADIUS_M, 1)])
        balls = h.balls_m()
        # one ball at the spot, the other queued behind it (either order)
        d = np.linalg.norm(balls[:, None, :] - spots[None, :, :], axis=2)
        assert min(d[0, 0] + d[1, 1], d[0, 1] + d[1, 0]) < 0.03, balls
    finally:
        h.cleanup()


def test_the_rig_config_matches_the_scene():
    """The step's geometry is data in the rig file: it must be the scene's."""
    cfg = yaml.safe_load(RIG.read_text())
    p = cfg["reset"]["steps"][0]["params"]
    h = hand(True, world="station-config")
    try:
        np.testing.assert_allclose(p["spot_m"], h.hand.station.spot_m(BALL_RADIUS_M), atol=1e-3)
        np.testing.assert_allclose(p["palm_center_m"], h.task.center_m, atol=1e-3)
        np.testing.assert_allclose(p["base_pos_m"], h.model.body("arm:base").pos, atol=1e-6)
        np.testing.assert_allclose(p["base_pos_m"], ResetArmParams().base_pos_m, atol=1e-6)
    finally:
        h.cleanup()


def test_the_arm_sim_sees_the_hands_balls_and_moves_in_the_hands_scene():
    h = hand(True, world="station-arm")
    arm = ResetArmSim(ResetArmParams(world="station-arm"))
    try:
        arm.configure()
        arm.activate()
        o = arm.read()
        np.testing.assert_array_equal(np.asarray(o.state[15:21]).reshape(2, 3), h.balls_m())
        target = np.zeros(8)
        target[1] = 0.3  # shoulder forward
        for _ in range(20):
            arm.write(target)
            h.write(hold_pose_action())
            h.tick()
            arm.tick()
        o2 = arm.read()
        assert o2.t_s == pytest.approx(h.sim_time_s)  # one clock: the hand's
        assert o2.state[1] == pytest.approx(0.3, abs=0.02)
    finally:
        arm.cleanup()
        h.cleanup()


def test_the_arm_sim_without_a_hand_scene_says_what_to_add():
    arm = ResetArmSim(ResetArmParams(world="nowhere", world_wait_s=0.1))
    with pytest.raises(LinkError, match=r"no simulated hand scene 'nowhere' with a reset station.*"
                                        r"params.sim.reset_station: true"):
        arm.configure()


@pytest.mark.parametrize("seed", range(5))
def test_ik_reaches_reachable_poses_with_the_tool_down(seed):
    """Targets made by forward kinematics of a random tool-down posture: reachable by
    construction; the solver must find a posture with the same tool point and axis."""
    ik = ArmIK((1.62, 0.95, -0.22))
    rng = np.random.default_rng(seed)
    rot = down_frame(np.array([0.0, 1.0, 0.0]))
    q_true, _ = ik.solve(READY_Q_RAD, np.array([1.0, 0.95, 0.0]) + rng.uniform(-0.15, 0.15, 3), rot, iters=300)
    p, r = ik.fk(q_true)
    q, err = ik.solve(READY_Q_RAD + rng.uniform(-0.2, 0.2, 7), p, r, iters=300)
    p2, r2 = ik.fk(q)
    assert err < 1e-3 and np.linalg.norm(p2 - p) < 1e-3
    assert r2[:, 2] @ np.array([0.0, 0.0, -1.0]) > 0.999  # the approach axis points down
    np.testing.assert_allclose(r2, r, atol=2e-3)


def test_the_arm_udp_driver_and_controller_refuse_bad_frames_and_flag_silence():
    """The real driver against the controller the emulator runs (in-process here)."""
    import socket
    import time

    from hilstack.drivers.reset_arm.driver import ResetArmDriver
    from hilstack.drivers.reset_arm.protocol import encode_command
    from hilstack.sim_backends.reset_arm.server import ArmServer
    from tests.helpers import free_port

    h = hand(True, world="station-udp")
    port = free_port()
    srv = ArmServer(h, port)
    drv = ResetArmDriver(ResetArmParams(port=port, connect_timeout_s=5.0), backend="emulated")

    def serve(seconds: float, send: bool = True) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            srv.poll(time.monotonic())
            if send:
                srv.send_state()
            time.sleep(0.01)

    th = threading.Thread(target=serve, args=(1.0,))
    th.start()
    try:
        drv.configure()
        drv.activate()
        th.join()
        assert drv.read().ok
        # a frame that is not a state, sent to the driver's socket: counted and dropped
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(b"garbage", drv._sock.getsockname())
            # a command with NaN to the controller: refused, the arm keeps its targets
            ctrl_before = h.data.ctrl[srv.ix.ctrl].copy()
            s.sendto(encode_command(1, np.full(8, np.nan)), ("127.0.0.1", port))
        serve(0.2)
        o = drv.read()
        assert drv.bad_frames == 1 and o.ok
        assert srv.bad_frames == 1
        np.testing.assert_array_equal(h.data.ctrl[srv.ix.ctrl], ctrl_before)
        # the controller goes silent: the reading turns stale, not ok
        serve(0.4, send=False)
        o = drv.read()
        assert not o.ok and o.flags["stale_telemetry"]
    finally:
        drv.cleanup()
        srv.close()
        h.cleanup()
