"""VelociRoACH MuJoCo backend: locomotion, firmware, battery, terrains, perturbations, sensors.

Lockstep sim only: no sleeps, no wall clock. Speeds at 9 rev/s (0.6 of max_leg_vel_rps
= 15 rev/s) on carpet are ~0.8 m/s in this model; tests accept 0.3-1.5 m/s.
"""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from hilstack.configs.schema import ConfigError
from hilstack.drivers.registry import make_driver
from hilstack.drivers.velociroach.config import STATE_NAMES, VelociRoachParams
from hilstack.sim_backends.velociroach.backend import VelociRoachSim
from hilstack.sim_backends.velociroach.firmware import FAULT_WATCHDOG

IX = {n: i for i, n in enumerate(STATE_NAMES)}


def make(**sim) -> VelociRoachSim:
    s = VelociRoachSim(VelociRoachParams(sim=sim))
    s.configure()
    s.activate()
    return s


def drive(s: VelociRoachSim, left: float, right: float, seconds: float) -> np.ndarray:
    for _ in range(round(seconds / s.spec.period_s)):
        s.write([left, right])
        s.tick()
    return s.read().state


def yaw_of(state: np.ndarray) -> float:
    return math.atan2(state[IX["sin_yaw"]], state[IX["cos_yaw"]])


def speed_mps(seconds: float = 2.0, cmd: float = 9.0, **sim) -> float:
    """Mean ground speed after a 1 s spin-up."""
    s = make(**sim)
    a = drive(s, cmd, cmd, 1.0)
    b = drive(s, cmd, cmd, seconds)
    return math.hypot(b[0] - a[0], b[1] - a[1]) / seconds


def test_backend_from_registry_and_state_layout():
    d = make_driver("velociroach", backend="sim")
    assert isinstance(d, VelociRoachSim)
    assert d.spec.state.names == STATE_NAMES and d.spec.action.names == ("leg_vel_l", "leg_vel_r")
    d.configure()
    st = d.read().state
    assert st.shape == (24,)
    assert st[IX["z"]] > 0.01 and st[IX["cos_yaw"]] == pytest.approx(1, abs=0.01)
    assert 3.7 < st[IX["vbat"]] < 4.2
    d.cleanup()


@pytest.mark.parametrize("yaw0", [0.0, math.pi / 2])
def test_equal_speeds_walk_forward_in_heading(yaw0):
    s = make()
    s.reset(x=0.5, y=-0.5, yaw=yaw0)
    a = drive(s, 9.0, 9.0, 1.0)
    b = drive(s, 9.0, 9.0, 2.0)
    d = b[:2] - a[:2]
    heading = np.array([math.cos(yaw0), math.sin(yaw0)])
    forward_mps = float(d @ heading) / 2.0
    assert 0.3 < forward_mps < 1.5
    assert abs(float(d @ np.array([-heading[1], heading[0]]))) < 0.5 * abs(float(d @ heading))
    assert abs(math.remainder(yaw_of(b) - yaw0, 2 * math.pi)) < math.radians(30)


def test_unequal_speeds_turn_toward_slower_side():
    right_slow = drive(make(), 9.0, 4.0, 0.5)
    left_slow = drive(make(), 4.0, 9.0, 0.5)
    assert yaw_of(right_slow) < -math.radians(10)  # clockwise: toward the right (slower) side
    assert yaw_of(left_slow) > math.radians(10)


def test_zero_command_stays_still():
    s = make()
    a = drive(s, 0.0, 0.0, 0.5)
    b = drive(s, 0.0, 0.0, 3.0)
    assert np.linalg.norm(b[:2] - a[:2]) < 0.01
    assert abs(b[IX["crank_vel_l"]]) < 0.2 and abs(b[IX["crank_vel_r"]]) < 0.2


def test_pid_tracks_leg_velocity():
    s = make()
    s.firmware.set_leg_velocity(6.0, 6.0, s.sim_time_s)
    s.advance(1.0)
    # mean crank speed over 1 s from the unwrapped crank angle (the instantaneous speed
    # ripples with the stance load, which is physical)
    t0 = s.telemetry()
    samples = []
    for _ in range(100):
        s.firmware.set_leg_velocity(6.0, 6.0, s.sim_time_s)
        s.advance(0.01)
        samples.append(s.telemetry()["crank_vel_rps"])
    mean = np.mean(samples, axis=0)
    np.testing.assert_allclose(mean, [6.0, 6.0], rtol=0.04)
    assert s.telemetry()["t_fw_ms"] - t0["t_fw_ms"] == 1000


def test_watchdog_stops_motors():
    s = make()
    s.firmware.set_leg_velocity(8.0, 8.0, s.sim_time_s)
    s.advance(0.45)
    tel = s.telemetry()
    assert tel["faults"] & 1 == 0 and min(tel["crank_vel_rps"]) > 4.0
    s.advance(0.1)  # 0.55 s without a command
    tel = s.telemetry()
    assert tel["faults"] & 1 and tel["duty"] == [0.0, 0.0]
    s.advance(0.5)
    assert max(abs(v) for v in s.telemetry()["crank_vel_rps"]) < 0.5
    s.firmware.set_leg_velocity(5.0, 5.0, s.sim_time_s)  # a new command re-arms
    s.advance(0.2)
    assert s.telemetry()["faults"] & 1 == 0 and min(s.telemetry()["crank_vel_rps"]) > 2.0


def test_pwm_mode_and_battery_sag_under_load():
    s = VelociRoachSim(VelociRoachParams(action_mode="pwm", sim={"battery_resistance_ohm": 0.5}))
    s.configure()
    s.activate()
    rest = drive(s, 0.0, 0.0, 0.5)[IX["vbat"]]
    loaded = drive(s, 1.0, 1.0, 1.5)[IX["vbat"]]  # rate limit ramps the duty up
    assert s.firmware.duty_l == pytest.approx(1.0)
    assert rest - loaded > 0.1
    back = drive(s, 0.0, 0.0, 1.0)[IX["vbat"]]
    assert back > loaded + 0.08


def test_terrains_and_slope_change_speed():
    carpet = speed_mps()
    assert 0.3 < carpet < 1.5
    assert speed_mps(terrain="styrofoam") < 0.85 * carpet
    assert speed_mps(slope_deg=15) < 0.95 * carpet
    assert speed_mps(slope_deg=-15) > speed_mps(slope_deg=15)
    gravel = speed_mps(terrain="gravel", seed=1)
    assert 0.05 < gravel < 1.5


def test_payload_perturbation_mid_run_slows():
    s = make()
    a = drive(s, 9.0, 9.0, 1.0)
    b = drive(s, 9.0, 9.0, 1.5)
    free = np.linalg.norm(b[:2] - a[:2]) / 1.5
    s.set_perturbation("payload_kg", 0.05)
    c = drive(s, 9.0, 9.0, 0.5)
    d = drive(s, 9.0, 9.0, 1.5)
    towed = np.linalg.norm(d[:2] - c[:2]) / 1.5
    assert towed < 0.8 * free
    s.set_perturbation("payload_kg", 0.0)
    with pytest.raises(KeyError):
        s.set_perturbation("gremlins", 1)


def test_missing_leg_and_mocap_offset():
    s = make()
    base = drive(s, 9.0, 9.0, 1.0)
    s.set_perturbation("missing_leg", "lm")
    assert all(s.model.geom_contype[g] == 0 for g in s._leg_geoms["lm"])
    moved = drive(s, 9.0, 9.0, 1.0)
    assert np.linalg.norm(moved[:2] - base[:2]) > 0.1  # still walks, on five legs
    s.set_perturbation("missing_leg", None)
    assert s.model.geom_contype[s._leg_geoms["lm"][-1]] == 1
    s.set_perturbation("mocap_offset_m", [0.1, -0.2, 0.0])
    s.advance(0.05)
    t, pos, _ = s.mocap_pose()
    np.testing.assert_allclose(pos - s.data.qpos[0:3], [0.1, -0.2, 0.0], atol=0.02)
    np.testing.assert_allclose(s.read().state[:3] - s.true_position_m(), [0.1, -0.2, 0.0], atol=0.02)
    s.set_perturbation("mocap_offset_m", 0.0)
    s.advance(0.05)
    np.testing.assert_allclose(s.read().state[:3], s.true_position_m(), atol=0.01)


def test_bad_sim_key_names_field_and_file():
    with pytest.raises(ConfigError) as e:
        make_driver("velociroach", backend="sim", sim={"terain": "carpet"})
    msg = str(e.value)
    assert "params.sim.terain" in msg and "velociroach.yaml" in msg
    with pytest.raises(ConfigError, match=r"params\.sim\.terrain"):
        make_driver("velociroach", backend="sim", sim={"terrain": "lava"})


def test_mocap_latency_dropout_and_noise():
    s = make(mocap_rate_hz=100, mocap_latency_s=0.03, mocap_dropout=0.3, mocap_noise_m=0.002, seed=3)
    # legs held still by the PID; past the pose taken at reset (delivered at once, as if
    # the mocap system ran before the reset) and the settling of the stance
    s.firmware.stop(s.sim_time_s)
    s.advance(0.3)
    poses, nones = [], 0
    for _ in range(400):
        s.firmware.stop(s.sim_time_s)
        s.advance(0.01)
        p = s.mocap_pose()
        if p is None:
            nones += 1
            continue
        t, pos, q = p
        assert s.sim_time_s - 0.03 - 0.0105 <= t <= s.sim_time_s - 0.03 + 1e-9
        assert q.shape == (4,) and abs(np.linalg.norm(q) - 1) < 1e-9
        poses.append(pos)
    assert 0.2 < nones / 400 < 0.4
    std = np.std(np.array(poses)[:, 0])  # robot at rest: the spread is the noise
    assert 0.001 < std < 0.004
    assert s.health().dropped_frames == s.mocap_dropped > 0


def test_mocap_delivery_batches_give_what_sample_by_sample_delivery_gives():
    """The backend hands queued mocap samples to the pose input in batches (a vectorized
    search for the arrived ones); the rule is the sample-by-sample one: in order, each arrived
    sample sets whether the newest was lost, each kept one refreshes the input at its arrival
    (a non-finite one is counted, not used), the newest kept finite one is the pose."""
    from hilstack.drivers.base import Flag, Freshness

    s = make(seed=1)
    rng = np.random.default_rng(7)
    for trial in range(40):
        s.reset()  # an empty queue (the reset's own sample is delivered at once)
        ref_pose = Freshness("pose", 1.0, Flag.STALE_POSE)
        ref_pose.start(0.0)
        s.inputs["pose"].start(0.0)
        ref_latest, ref_ok = None, False
        s._mocap_latest, s._mocap_latest_ok, s._mocap_head, s._mocap_tail = None, False, 0, 0
        n = int(rng.integers(1, 40))
        ts = np.cumsum(rng.uniform(0.001, 0.01, n))
        ok = rng.random(n) > (0.3 if trial % 2 else 0.0)  # half the trials: every sample kept
        finite = rng.random(n) > (0.2 if trial % 3 == 0 else 0.0)
        rows = np.column_stack([ts + 0.005, ts, rng.normal(size=(n, 7)), ok, finite])
        rows[~finite, 2] = np.nan
        for row in rows.tolist():
            s._queue_mocap(tuple(row))
        pending = rows.tolist()
        nows = np.sort(np.append(rng.uniform(0.0, ts[-1] + 0.02, 3), ts[n // 2] + 0.005 - 5e-10))  # one within
        for now in nows.tolist():  # the 1e-9 tolerance of a sample's arrival: refreshed at now, not later
            s._deliver_mocap(now)
            while pending and pending[0][0] <= now + 1e-9:  # the rule, sample by sample
                t_arrive, t_s, p0, p1, p2, w, x, y, z, o, f = pending.pop(0)
                ref_ok = bool(o)
                if o:
                    ref_pose.update(min(t_arrive, now), bool(f))
                    if f:
                        ref_latest = (t_s, (p0, p1, p2), (w, x, y, z))
            assert s._mocap_latest == ref_latest and s._mocap_latest_ok == ref_ok
            got = s.inputs["pose"]
            assert (got.last_t_s, got.nonfinite_samples) == (ref_pose.last_t_s, ref_pose.nonfinite_samples)
            assert s._mocap_tail - s._mocap_head == len(pending)


def test_telemetry_packet():
    s = make()
    s.firmware.set_leg_velocity(5.0, 5.0, 0.0)
    s.advance(0.5)
    tel = s.telemetry()
    assert tel["t_fw_ms"] == 500 and isinstance(tel["t_fw_ms"], int)
    for k, n in (("gyro_rps", 3), ("accel_mps2", 3), ("crank_angle_rad", 2), ("crank_vel_rps", 2),
                 ("bemf_v", 2), ("duty", 2)):
        assert len(tel[k]) == n, k
    assert 3.5 < tel["vbat_v"] < 4.3 and tel["faults"] == 0
    assert all(0 <= a < 2 * math.pi for a in tel["crank_angle_rad"])
    # accelerometer at rest-ish reads gravity (specific force, +z up in the body frame)
    s.firmware.set_leg_velocity(0.0, 0.0, s.sim_time_s)
    s.advance(1.0)
    assert 7.0 < s.telemetry()["accel_mps2"][2] < 12.5
    assert np.mean(s.telemetry()["bemf_v"]) < 0.05


def _rollout(seed: int) -> np.ndarray:
    s = make(seed=seed, terrain="gravel", mocap_dropout=0.1)
    rng = np.random.default_rng(0)
    out = []
    for _ in range(20):
        s.write(rng.uniform(-15, 15, 2))
        s.tick()
        out.append(s.read().state)
    return np.array(out)


def test_deterministic_for_a_seed():
    a, b = _rollout(4), _rollout(4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, _rollout(5))


def test_rough_terrain_is_endless_and_positions_continuous():
    s = make(terrain="gravel", terrain_half_size_m=0.2, seed=2)
    s.reset(x=0.15, y=0.0)
    xy = []
    for _ in range(30):
        xy.append(drive(s, 12.0, 12.0, 0.1)[:2])
    true = s.true_position_m()
    assert np.any(s._tile_offset != 0)  # crossed the edge of the 0.4 m map at least once
    assert np.linalg.norm(true[:2] - s.read().state[:2]) < 0.05  # mocap reports the continuous position
    assert np.max(np.linalg.norm(np.diff(xy, axis=0), axis=1)) < 0.2  # no jumps at the wraps
    assert np.all(np.abs(s.data.qpos[0:2]) <= 0.2 + 0.05) and s.data.qpos[2] > 0


def test_stale_pose_is_flagged_in_sim_time():
    s = make(mocap_dropout=0.9, mocap_rate_hz=20, seed=1)  # a pose every 0.5 s on average
    stale = fresh = 0
    for _ in range(40):
        s.write([6.0, 6.0])
        s.tick()
        obs = s.read()
        age = s.health().extra["pose_age_s"]
        assert obs.flags["stale_pose"] == (age is None or age > s.params.pose_deadline_s)
        assert obs.ok == (not obs.flags["stale_pose"])
        stale += obs.flags["stale_pose"]
        fresh += not obs.flags["stale_pose"]
    assert stale > 5 and fresh > 5
    good = make()  # 120 Hz, no dropout: never stale
    for _ in range(10):
        good.tick()
        assert good.read().ok and good.health().extra["pose_age_s"] < 0.02


def _max_safe_step_rps(sim) -> float:
    """The largest leg-velocity setpoint step whose current spike (the PID's duty jump
    (ff + kp·vbat)·dw over R, before the back-EMF moves) stays under the over-current fault
    at a full battery: the derivation of the default rate limit (configs/robots/velociroach.yaml)."""
    from hilstack.sim_backends.velociroach.firmware import default_ff_v_per_rps

    ff = default_ff_v_per_rps(sim.motor_k_v_s_per_rad, sim.gear_ratio)
    return sim.overcurrent_a * sim.motor_resistance_ohm / (ff + sim.kp_duty_per_rps * sim.battery_full_v)


def test_default_rate_limit_follows_from_the_motor_model():
    from hilstack.sim_backends.velociroach.backend import SimParams

    p = VelociRoachParams()
    step = p.max_leg_accel_rps2 * p.period_s
    assert step <= _max_safe_step_rps(SimParams()) < 1.1 * step  # derived, not just "some" bound
    # a full reversal through the rate-limited contract never trips the motor fault ...
    s = make()
    for _ in range(10):
        s.write([-15.0, -15.0])
        s.tick()
    faults = 0
    for _ in range(10):
        for _ in range(5):  # a controller hammering the limit several times per period
            s.write([15.0, 15.0])
        s.tick()
        faults |= s.firmware.faults
    assert s.read().flags["motor_fault"] is False and not faults & 4
    assert s.held_command == pytest.approx([15.0, 15.0])
    # ... while the same reversal as one step (what the old per-write limit let through) does
    s.firmware.set_leg_velocity(-15.0, -15.0, s.sim_time_s)
    faults = 0
    for _ in range(40):
        s.advance(0.001)
        if _ == 20:
            s.firmware.set_leg_velocity(15.0, 15.0, s.sim_time_s)
        faults |= s.firmware.faults
    assert faults & 4


def test_reset_rewinds_time_and_holds_what_the_rebooted_firmware_runs():
    s = make()
    drive(s, 9.0, 9.0, 0.5)
    assert s.held_command == pytest.approx([9.0, 9.0])
    s.reset()
    assert s.sim_time_s == 0.0 and s.held_command == pytest.approx([0.0, 0.0])
    step = s.params.max_leg_accel_rps2 * s.params.period_s
    assert s.write([15.0, 15.0]) == pytest.approx([step, step])  # ramps from zero again
    assert s.write([15.0, 15.0]) == pytest.approx([step, step])


def test_leg_speed_scale_slows_one_side_and_default_is_unchanged():
    # the default (1, 1) is the nominal physics, bit for bit
    np.testing.assert_array_equal(drive(make(), 9.0, 9.0, 0.5), drive(make(leg_speed_scale=(1.0, 1.0)), 9.0, 9.0, 0.5))
    # left side at 60 %: equal commands turn the robot left, and the left crank runs at 0.6 x 9 rev/s
    s = make(leg_speed_scale=(0.6, 1.0))
    nominal = yaw_of(drive(make(), 9.0, 9.0, 0.5))  # about -8 degrees
    assert yaw_of(drive(s, 9.0, 9.0, 0.5)) > nominal + math.radians(30)  # about +54
    assert yaw_of(drive(make(leg_speed_scale=(1.0, 0.6)), 9.0, 9.0, 0.5)) < nominal - math.radians(30)
    samples = [drive(s, 9.0, 9.0, 0.1)[[IX["crank_vel_l"], IX["crank_vel_r"]]] for _ in range(5)]
    np.testing.assert_allclose(np.mean(samples, 0), [5.4, 9.0], atol=0.6)
    with pytest.raises(ConfigError, match="leg_speed_scale"):
        make(leg_speed_scale=(0.0, 1.0))


def _fingerprint(inline: bool, action_mode: str = "leg_velocity", compiled: bool = False, x0: float = 0.0,
                 **sim) -> list:
    """Every reading of a run that drives, goes quiet past the watchdog (it trips inside a
    tick), drives again, changes the mocap offset and heading miscalibration, and tows a
    payload; with the PID inlined (in Python, or compiled by numba: its loop takes the mocap
    samples too) or through Firmware.tick. The mocap samples taken, dropped and delivered
    (``mocap_pose``) and the rough terrain's wrap are part of the fingerprint."""
    s = VelociRoachSim(VelociRoachParams(action_mode=action_mode, sim={"seed": 2, **sim}))
    s.inline_firmware = inline
    s.compiled_firmware = compiled
    s.configure()
    s.activate()
    s.reset(x=x0)
    rng = np.random.default_rng(0)
    hi = s.spec.action.high
    out = []
    for i in range(40):
        if i == 4:
            s.set_perturbation("mocap_offset_m", [0.01, -0.02, 0.003])
            s.set_perturbation("heading_offset_deg", 7.0)
        if i == 25:
            s.set_perturbation("payload_kg", 0.05)
        if not 8 <= i < 16:  # 0.8 s without a command: the 0.5 s watchdog trips mid-tick
            s.write(rng.uniform(-hi, hi))
        s.tick()
        r = s.read()
        fw = s.firmware
        out.append((r.state.tolist(), r.ok, sorted(r.flags.items()), fw.t_fw_ms, fw.duty_l, fw.duty_r, fw.faults,
                    fw.watchdog_tripped, fw._int_l, fw._int_r, fw._prev_e_l, fw._prev_e_r,
                    s.mocap_samples, s.mocap_dropped, s._tile_offset.tolist(), s.data.qpos.tolist()))
        if i % 6 == 0:  # between ticks: samples that arrive later than a read
            s.advance(0.023)
            p = s.mocap_pose()
            out.append(None if p is None else (p[0], p[1].tolist(), p[2].tolist()))
    s.cleanup()
    return out


#: a rough terrain the robot crosses the edge of (the wrap), at 333 Hz with 30 % of the samples lost
_MOCAP_HEAVY = {"terrain": "gravel", "terrain_half_size_m": 0.2, "x0": 0.19, "mocap_rate_hz": 333.0,
                "mocap_latency_s": 0.012, "mocap_dropout": 0.3}


@pytest.mark.parametrize("action_mode,sim", [("leg_velocity", {}), ("pwm", {}),
                                             ("leg_velocity", {"battery_soc": 0.0}),
                                             ("leg_velocity", _MOCAP_HEAVY)])
def test_inlined_firmware_pid_gives_the_same_floats_as_firmware_tick(action_mode, sim):
    a, b = _fingerprint(True, action_mode, **sim), _fingerprint(False, action_mode, **sim)
    assert any(x[7] for x in a if x and len(x) > 7)  # the watchdog did trip on the way
    if "battery_soc" in sim:
        assert any(x[6] & ~FAULT_WATCHDOG for x in a if x and len(x) > 7)  # low-battery / motor faults set
    if "x0" in sim:
        readings = [x for x in a if x and len(x) > 7]
        assert any(x[14] != [0.0, 0.0, 0.0] for x in readings)  # crossed the map's edge: wrapped
        assert 0 < readings[-1][13] < readings[-1][12]  # some samples dropped, not all
    assert a == b
    if action_mode == "leg_velocity" and compiled_loop() is not None:  # the speed extra: the same floats
        assert _fingerprint(True, action_mode, compiled=True, **sim) == a


def compiled_loop():
    from hilstack.sim_backends.velociroach.compiled import kernel

    return kernel()


def test_the_compiled_loop_runs_when_numba_is_installed():
    """With numba (the speed extra) the sim's 1 kHz loop runs compiled; without it, in Python."""
    pytest.importorskip("numba", reason="numba (hilstack[speed]) is not installed: the loop runs in Python")
    s = VelociRoachSim(VelociRoachParams(sim={"seed": 2}))
    s.configure()
    s.activate()
    assert s._kernel() is not None
    s.write(np.array([3.0, 3.0]))
    for _ in range(5):
        s.tick()
    assert s.firmware.t_fw_ms == 500 and s.read().state[0] > 0.0  # ran the ticks, walked forward
    s.cleanup()


def test_the_compiled_loops_draws_are_numpys_from_the_same_generator():
    """The compiled loop draws the mocap noise through the Generator's bit generator with
    numpy's algorithms: 15000 samples' (random, 6 x standard_normal) equal numpy's, the ziggurat's
    rare branches included, and the Generator goes on from where they stopped."""
    pytest.importorskip("numba", reason="numba (hilstack[speed]) is not installed: the loop runs in Python")
    from hilstack.sim_backends.velociroach.backend import bit_generator_pointers
    from hilstack.sim_backends.velociroach.compiled import draws

    for seed in (0, 1):
        ours, ref = np.random.default_rng(seed), np.random.default_rng(seed)
        out = np.empty((15000, 7))
        draws(*bit_generator_pointers(ours), out)
        want = np.array([[ref.random(), *ref.standard_normal(6)] for _ in range(len(out))])
        np.testing.assert_array_equal(out, want)
        assert ours.random() == ref.random()


def test_bench_sim_times_each_part_of_a_period_against_the_raw_peer(monkeypatch):
    """`hil bench sim`: the backend, the same loop in Python and raw mj_step take turns; the
    CPU-time ratios are raw / contract over the same periods, and each part is reported."""
    from hilstack.tools import bench_sim

    monkeypatch.setattr(bench_sim, "run_bench_batch", lambda **kw: {})
    r = bench_sim.run_bench_sim(0.4, block_s=0.2)
    assert r["blocks"] == 2 and r["robot_s"] == pytest.approx(0.4)
    per = r["cpu"]["per_period"]
    assert set(per) == {"read", "write", "tick", "raw", "read_python_loop", "write_python_loop", "tick_python_loop"}
    assert all(0 < v["p50_us"] <= v["p99_us"] for v in per.values())
    assert 0 < r["cpu"]["ratio"] < 2 and 0 < r["cpu"]["ratio_python_loop"] < 2
    assert r["compiled_loop"] is True or "hilstack[speed]" in r["compiled_loop"]


@pytest.mark.parametrize("sim", [{}, {"camera_px": 16}, {"terrain": "gravel", "camera_px": 16}])
def test_a_deep_copy_is_an_independent_sim_at_the_same_instant(sim):
    """Planners and calibration copy a sim as an oracle (``copy.deepcopy``). The copy failed
    with a camera (its GL context), and without one it ran wrong: the compiled loop kept
    stepping through views of the original's MjData. Now the copy goes on exactly as the
    original does under the same commands, renders its own images, and stepping it leaves
    the original where a sim never copied is."""
    import copy

    ref, a = make(**sim), make(**sim)
    rng = np.random.default_rng(3)
    cmds = rng.uniform(-6.0, 9.0, size=(16, 2))
    for c in cmds[:4]:
        for s in (ref, a):
            s.write(c)
            s.tick()
    a.read()  # a reading (with the camera's first image) before the copy
    ref.read()
    b = copy.deepcopy(a)
    # the copy alone for a while: the original (and its noise streams) must not notice
    for c in cmds[8:]:
        b.write(c)
        b.tick()
    for c in cmds[4:8]:
        for s in (ref, a):
            s.write(c)
            s.tick()
    oa, oref = a.read(), ref.read()
    np.testing.assert_array_equal(oa.state, oref.state)
    # the copy from where it was made: as the original went, command for command
    c2 = copy.deepcopy(a)
    for c in cmds[8:]:
        for s in (a, c2):
            s.write(c)
            s.tick()
    o1, o2 = a.read(), c2.read()
    np.testing.assert_array_equal(o1.state, o2.state)
    assert o1.t_s == o2.t_s and o1.ok and o2.ok
    if sim.get("camera_px"):
        assert o2.extras["image"].shape == (16, 16, 3)
        np.testing.assert_array_equal(o1.extras["image"], o2.extras["image"])
    for s in (ref, a, b, c2):
        s.cleanup()


def test_configure_loads_the_compiled_loop_before_the_first_tick():
    """The compiled loop is loaded (or compiled) at configure, for the argument types the ticks
    pass, so the first tick, which may answer a reset under a supervisor's 2 s state timeout,
    does not stall on it (seconds with a warm cache, tens without). In a fresh process: one
    that ran the loop before would pass whatever configure did."""
    pytest.importorskip("numba")
    code = """
from hilstack.drivers.velociroach.config import VelociRoachParams
from hilstack.sim_backends.velociroach.backend import VelociRoachSim
from hilstack.sim_backends.velociroach.compiled import kernel
run = kernel()[0]
s = VelociRoachSim(VelociRoachParams())
assert s.compiled_firmware and not run.signatures
s.configure()
loaded = list(run.signatures)
assert loaded, "configure left the compiled loop unloaded"
s.activate()
for _ in range(3):
    s.write(s.spec.action.high * 0.5)
    s.tick()
    s.read()
assert list(run.signatures) == loaded, "the ticks needed another specialization"
"""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
