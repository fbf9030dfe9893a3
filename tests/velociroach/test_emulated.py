"""The real VelociRoACH driver against the firmware emulator (a separate process on a pty,
MuJoCo underneath), including protocol faults and radio loss.

Waits are on conditions with timeouts (telemetry arriving, a flag flipping), never fixed
sleeps; the only pacing is the driver's own ``tick()`` at the control period.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hilstack.drivers.base import Lifecycle, LinkError
from hilstack.drivers.velociroach.config import STATE_NAMES, VelociRoachParams
from hilstack.drivers.velociroach.driver import VelociRoachDriver
from hilstack.drivers.velociroach.link import addr64, xbee_tx64
from hilstack.drivers.velociroach.mavlink import BASE_COMPID, BASE_SYSID, MavEncoder

REPO = Path(__file__).resolve().parents[2]
I_VEL_L, I_VEL_R = STATE_NAMES.index("crank_vel_l"), STATE_NAMES.index("crank_vel_r")
I_X = STATE_NAMES.index("x")


def make(**params) -> VelociRoachDriver:
    return VelociRoachDriver(VelociRoachParams(**params), backend="emulated")


def wait_for(cond, timeout_s: float, what: str, step=None):
    """Poll ``cond()`` (calling ``step()`` between polls, e.g. read-write-tick) until truthy."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        if step is not None:
            step()
        else:
            time.sleep(0.01)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def test_heartbeat_tracking_watchdog_gains_and_tlog(tmp_path):
    tlog = tmp_path / "roach.tlog"
    drv = make(tlog=str(tlog))
    with drv:
        h = drv.health()
        assert h.ok and h.last_heartbeat_s is not None

        # command -> the 1 kHz PID makes the cranks track it
        target = np.array([6.0, 6.0])

        def drive():
            drv.write(target)
            drv.tick()

        def tracking():
            s = drv.read().state
            return abs(s[I_VEL_L] - 6.0) < 1.0 and abs(s[I_VEL_R] - 6.0) < 1.0

        wait_for(tracking, 3.0, "crank velocity to track 6 rev/s", step=drive)
        vels = []
        for _ in range(5):
            drive()
            vels.append(drv.read().state[[I_VEL_L, I_VEL_R]])
        np.testing.assert_allclose(np.mean(vels, axis=0), target, atol=1.0)
        # silence from here: the firmware's watchdog stops the motors 500 ms after the last
        # command (counted on the firmware's own clock from the tlog below)
        sent = drv.read().extras["cmd_seq_sent"]
        acked = wait_for(lambda: (o := drv.read()).extras["last_cmd_seq"] == sent and o, 1.0, "the last command's echo")
        assert not acked.flags["watchdog"]
        assert drv.health().latency_s is not None and drv.health().latency_s > 0  # an echo matched a command

        # PID gains: set, read back (not commands: the watchdog keeps counting)
        assert drv.set_pid_gains(0.06, 1.2, 0.0) == pytest.approx((0.06, 1.2, 0.0), rel=1e-6)
        assert drv.get_pid_gains() == pytest.approx((0.06, 1.2, 0.0), rel=1e-6)

        obs = wait_for(lambda: (o := drv.read()).flags["watchdog"] and o, 2.0, "the watchdog fault bit")
        assert obs.extras["duty"] == [0.0, 0.0]
        wait_for(lambda: np.all(np.abs(drv.read().state[[I_VEL_L, I_VEL_R]]) < 0.5), 2.0, "the cranks to stop")
        assert any("watchdog" in t for t in drv.health().extra["status_text"])
        assert drv.health().corrupt_frames == 0

    # every frame of the session, both ways, readable by pymavlink
    from pymavlink import mavutil

    mlog = mavutil.mavlink_connection(str(tlog), dialect="velociroach")
    counts: dict[str, int] = {}
    while (m := mlog.recv_match()) is not None:
        counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
    assert counts.get("ROACH_TELEMETRY", 0) > 50
    assert counts.get("ROACH_LEG_VELOCITY_CMD", 0) >= 5
    assert counts.get("HEARTBEAT", 0) >= 2 and counts.get("ROACH_PID_GAINS", 0) == 2

    # the watchdog window in firmware ticks (t_fw_ms, 1 kHz), from every telemetry packet:
    # the command arrived after the last packet that did not echo it and no later than the
    # first that did; the trip shows in the first packet with the watchdog bit
    mlog = mavutil.mavlink_connection(str(tlog), dialect="velociroach")
    tel = []
    while (m := mlog.recv_match(type="ROACH_TELEMETRY")) is not None:
        tel.append((m.time_fw_ms, m.last_cmd_seq, m.faults))
    i_ack = next(i for i, t in enumerate(tel) if t[1] == sent)
    i_trip = next(i for i, t in enumerate(tel) if i > i_ack and t[2] & 1)
    assert not any(t[2] & 1 for t in tel[i_ack:i_trip])  # order: no trip before it is due
    assert tel[i_trip][0] - tel[i_ack - 1][0] >= 500  # not earlier than 500 ticks after the command
    # and no later than 500 ticks plus the telemetry spacing (10 ms; up to 50 ms when the
    # emulator catches up on a loaded machine)
    assert tel[i_trip][0] - tel[i_ack][0] <= 501 + 60


def test_corrupt_frames_both_ways_and_emulator_death():
    drv = make(emulator={"corrupt_every": 10, "garbage": True})
    with drv:
        # robot -> base: injected bad checksums, bad CRCs and noise are counted and skipped
        def enough():
            h = drv.health()
            return (h.extra["bad_xbee_checksum"] >= 2 and h.extra["bad_mavlink"] >= 2
                    and h.extra["garbage_runs"] >= 2 and h)

        h = wait_for(enough, 5.0, "injected corrupt frames to be counted", step=drv.tick)
        assert h.corrupt_frames >= 6 and h.frames_received > 30
        obs = drv.read()
        assert obs.ok and np.all(np.isfinite(obs.state))

        # base -> robot: the firmware rejects and counts broken frames, keeps the good ones
        enc = MavEncoder(BASE_SYSID, BASE_COMPID)
        good = enc.leg_velocity(999, 1.0, 1.0, 15.0)
        bad_sum = bytearray(xbee_tx64(addr64(drv.params.robot_addr64), good))
        bad_sum[-1] ^= 0x33
        bad_crc = bytearray(good)
        bad_crc[-4] ^= 0x01
        drv.link.send_raw(bytes(bad_sum))
        drv.link.send_raw(xbee_tx64(addr64(drv.params.robot_addr64), bytes(bad_crc)))
        drv.link.send_raw(b"\x01\x02\x03")
        wait_for(lambda: (drv.health().extra["robot_rx_corrupt"] or 0) >= 3, 2.0, "the robot to count 3 bad frames")

        # the emulator process dies (device unplugged): LinkError (within the bounded wait), never a hang
        drv.emulator.kill()
        with pytest.raises(LinkError, match="unplugged"):
            wait_for(lambda: drv.read() is None, 2.0, "a LinkError")
        assert drv.health().ok is False
        assert drv.lifecycle is Lifecycle.UNCONFIGURED and "unplugged" in drv.last_error


def test_radio_silence_shows_in_health_and_the_watchdog_stops_the_robot():
    # the error path for a frozen robot is tested below; here the outage may last
    # 1 s of radio before the outage: the robot moves first, even when the machine is loaded
    drv = make(emulator={"silence_after_s": 1.0}, link_timeout_periods=100)  # 10 s: the most allowed
    with drv:
        cmd = np.array([9.0, 9.0])

        def drive():
            drv.write(cmd)  # keeps commanding through the outage: nothing arrives
            drv.tick()

        wait_for(lambda: drv.read().state[I_X] > 0.05, 3.0, "the robot to move", step=drive)
        h = wait_for(lambda: (h := drv.health()).ok is False and h, 3.0, "health to report the outage", step=drive)
        wait_for(lambda: drv.health().link_quality < 0.05, 2.0, "link quality to drop", step=drive)
        obs = drv.read()  # a copy under a lock: answers at once, telemetry or not
        assert obs.ok is False and obs.flags["stale_telemetry"]
        assert h.extra["telemetry_age_s"] > 0.3

        # mocap still sees the robot: its own watchdog stopped it although we kept commanding
        def stopped():
            x0 = drv.read().state[I_X]
            for _ in range(3):
                drive()
            return abs(drv.read().state[I_X] - x0) < 0.005

        wait_for(stopped, 3.0, "the robot to stop on its watchdog", step=drive)


def test_hil_drive_emulated_moves_forward_with_a_clean_link():
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    r = subprocess.run(
        [sys.executable, "-m", "hilstack.tools.cli", "drive", "velociroach", "--backend", "emulated",
         "--action", "0.6,0.6", "--seconds", "3", "--json"],
        capture_output=True, text=True, timeout=60, cwd=REPO, env=env,
    )
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["backend"] == "emulated" and out["seconds"] == 3.0
    assert out["forward_m"] > 0.3 and out["distance_m"] > 0.3
    assert math.isfinite(out["final_pose"]["x"]) and math.isfinite(out["final_pose"]["yaw"])
    link = out["link"]
    assert link["corrupt_frames"] == 0 and link["frames_received"] > 100 and link["frames_sent"] >= 30
    assert "dropped_frames" in link


def test_sigterm_to_hil_drive_stops_the_robot_and_still_reports(tmp_path):
    """SIGTERM (a supervisor, `timeout`, a CI runner) ended `hil drive` with the robot
    moving, left to its device's watchdog; now it ends the drive: the stop goes out over the
    link and the summary is printed, exit 0."""
    import signal

    tlog = tmp_path / "drive.tlog"
    p = subprocess.Popen([sys.executable, "-m", "hilstack.tools.cli", "drive", "velociroach", "--backend", "emulated",
                          "--action", "0.6,0.6", "--seconds", "120", "--tlog", str(tlog)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                         env={**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"})
    try:
        first = p.stdout.readline()  # "velociroach (emulated): driving for 120 s" once active
        assert "driving for 120 s" in first, p.stderr.read() if p.poll() is not None else first
        time.sleep(1.0)
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, err
    assert "stopped early by a stop signal" in out and "link ok=" in out, out
    cmds = last_leg_commands(tlog)
    assert any(a > 0 for a, _ in cmds), "it drove before the signal"
    assert cmds[-1] == (0.0, 0.0), "the last command on the link must be the stop"


def last_leg_commands(tlog: Path) -> list[tuple[float, float]]:
    from pymavlink import mavutil

    mlog = mavutil.mavlink_connection(str(tlog), dialect="velociroach")
    out = []
    while (m := mlog.recv_match(type="ROACH_LEG_VELOCITY_CMD")) is not None:
        out.append((m.left_rps, m.right_rps))
    return out


def test_frozen_robot_takes_the_error_path_after_the_stated_periods_and_stops(tmp_path):
    """Telemetry stops with the link open: stale first (ok False), then after
    link_timeout_periods the error path: the stop is sent, LinkError, UNCONFIGURED."""
    tlog = tmp_path / "frozen.tlog"
    # 20 periods (2 s): the stale window before the error stays observable on a loaded machine
    drv = make(emulator={"silence_after_s": 0.2}, tlog=str(tlog), link_timeout_periods=20)
    with pytest.raises(LinkError) as err:
        with drv:
            seen_stale = ticks_after_stale = 0
            while True:  # ends with the LinkError (bounded below)
                obs = drv.read()
                if obs.flags["stale_telemetry"]:
                    assert obs.ok is False and drv.lifecycle is Lifecycle.ACTIVE
                    seen_stale += 1
                if seen_stale:
                    ticks_after_stale += 1
                    assert ticks_after_stale <= 40, "no error path 40 periods after telemetry went stale"
                drv.write([5.0, 5.0])
                drv.tick()
    assert seen_stale >= 1, err.value  # order: stale before the error
    assert "no usable telemetry" in str(err.value) and "20 control periods" in str(err.value)
    assert drv.lifecycle is Lifecycle.UNCONFIGURED and "no usable telemetry" in drv.last_error
    cmds = last_leg_commands(tlog)
    assert cmds[-1] == (0.0, 0.0) and (5.0, 5.0) in cmds  # the stop went out while the port was open


def test_reader_crash_on_a_healthy_link_still_sends_the_stop(tmp_path):
    tlog = tmp_path / "crash.tlog"
    drv = make(tlog=str(tlog))
    with drv:
        for _ in range(3):
            drv.write([4.0, 4.0])
            drv.tick()
        real_handle = drv._handle

        def buggy(m, now):  # a bug in the reader (not a link fault)
            if m.get_type() == "ROACH_TELEMETRY":
                raise ZeroDivisionError("bug in telemetry handling")
            real_handle(m, now)

        drv._handle = buggy
        with pytest.raises(LinkError, match="reader crashed"):
            wait_for(lambda: drv.read() is None, 2.0, "the reader crash to surface")
        assert drv.lifecycle is Lifecycle.UNCONFIGURED and "ZeroDivisionError" in drv.last_error
        assert "stop was not sent" not in drv.last_error
    cmds = last_leg_commands(tlog)
    assert cmds[-1] == (0.0, 0.0) and cmds[-2] != (0.0, 0.0)


def test_stale_pose_and_nan_telemetry_are_flagged_not_hidden():
    drv = make(emulator={"pose_silence_after_s": 0.3, "nonfinite_telemetry_every": 2})
    with drv:
        def drive():
            drv.write([9.0, 9.0])
            drv.tick()

        first = wait_for(lambda: (o := drv.read()).flags["stale_pose"] is False and o, 2.0, "a fresh pose")
        wait_for(lambda: drv.health().extra["pose_age_s"] < drv.params.pose_deadline_s, 2.0, "a young pose")
        # NaN telemetry: flagged, ok False, and the state keeps the last finite values (no zeros)
        nan_obs = wait_for(lambda: (o := drv.read()).flags["nonfinite_input"] and o, 3.0, "a NaN telemetry",
                           step=drive)
        assert nan_obs.ok is False and np.all(np.isfinite(nan_obs.state))
        assert drv.health().extra["telemetry_nonfinite_samples"] > 0
        # the mocap stream stops while the robot drives: x freezes, and says so (the
        # telemetry stays fresh: conditions, not single readings, tolerate a loaded machine)
        stale = wait_for(lambda: (o := drv.read()).flags["stale_pose"] and not o.flags["stale_telemetry"] and o,
                         3.0, "the pose to go stale", step=drive)
        assert stale.ok is False
        h = wait_for(lambda: (h := drv.health()).extra["telemetry_age_s"] < drv.params.telemetry_deadline_s and h,
                     2.0, "a health report with fresh telemetry")
        assert h.ok is False and h.extra["pose_age_s"] > drv.params.pose_deadline_s
        for _ in range(3):
            drive()
        later = drv.read()
        # the robot walks on (cranks turning, telemetry fresh) while x stays frozen, flagged
        assert later.state[I_X] == stale.state[I_X] != first.state[I_X]
        assert later.flags["stale_pose"] and not later.ok and min(later.state[[I_VEL_L, I_VEL_R]]) > 3.0
        assert drv.lifecycle is Lifecycle.ACTIVE  # a stale pose is not a dead robot


def test_emulator_section_is_typed():
    from hilstack.configs.schema import ConfigError
    from hilstack.drivers.registry import make_driver

    with pytest.raises(ConfigError) as e:
        make_driver("velociroach", backend="emulated", emulator={"corupt_every": 3})
    assert "params.emulator.corupt_every" in str(e.value) and "velociroach.yaml" in str(e.value)
    with pytest.raises(ConfigError, match=r"params\.emulator\.realtime_factor"):
        make_driver("velociroach", backend="emulated", emulator={"realtime_factor": "fast"})


def test_hil_drive_shows_why_the_emulator_did_not_start_and_keeps_its_log(tmp_path):
    cfg = tmp_path / "roach.yaml"
    cfg.write_text("robot: velociroach\nbackend: emulated\nparams:\n  emulator: {physics: 'no_such_module:Physics'}\n")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    r = subprocess.run(
        [sys.executable, "-m", "hilstack.tools.cli", "drive", str(cfg), "--backend", "emulated", "--action", "0.1,0.1",
         "--seconds", "0.2"],
        capture_output=True, text=True, timeout=60, cwd=REPO, env=env,
    )
    assert r.returncode == 1
    msg = r.stderr.strip()
    assert "emulator exited with code 1 before it was ready" in msg
    assert "No module named 'no_such_module'" in msg  # the log's last lines, on the one line shown
    log = Path(msg.split("(full log: ")[1].rstrip(")"))
    try:
        assert log.is_file() and "no_such_module" in log.read_text()
    finally:
        log.unlink(missing_ok=True)


def test_bridge_states_carry_the_command_that_moved_the_robot(rig_bus):
    """On the wall clock the driver node must stamp each state with the command held during
    the period that ended with it (what ``learning/recordings.py`` pairs as the action of a
    transition). It used to apply the newest command first and read right after, so the
    first state carrying a new command still showed the old one's effect: every recorded
    emulated/real transition was one period off (docs/mbrl.md, "Wall-clock rigs")."""
    import threading

    from hilstack.bus import keys
    from hilstack.bus.schemas import RobotState, decode
    from hilstack.configs.schema import load_rig, rig_robot_config
    from hilstack.control.controller_node import ControllerNode
    from hilstack.drivers.bridge import DriverNode
    from hilstack.drivers.registry import make_driver

    rig = load_rig("roach_emulated")
    bus = rig_bus("roach_emulated")  # its access control: this driver node is the rig's router
    node = DriverNode(make_driver(rig_robot_config(rig, "roach")), rig.name, "roach", bus,
                      handle_signals=False, estop_sync_s=0.3)
    th = threading.Thread(target=node.serve, daemon=True)
    th.start()
    try:
        with ControllerNode(rig.name, "roach", bus, handle_signals=False, state_timeout_s=10) as ctl:
            ctl.wait_ready(30)
            states = ctl.subscribe(keys.state(rig.name, "roach"), RobotState, latest=False, capacity=512)
            got: list[RobotState] = []
            # 0 for 0.5 s, then 6 rev/s (0.4 normalized), a command every 50 ms (two per period)
            t0 = time.monotonic()
            while time.monotonic() - t0 < 1.5:
                a = 0.0 if time.monotonic() - t0 < 0.5 else 0.4
                ctl.send(np.array([a, a]), 0)
                time.sleep(0.05)
                got += [decode(p, RobotState) for _, p in states.drain()]
    finally:
        node.stop_event.set()
        th.join(10)
        node.close()
    got = [m for m in got if m.action]
    first = next(i for i, m in enumerate(got) if m.action[0] > 3.0)
    assert 0 < first < len(got) - 5
    # the first state stamped with 6 rev/s was measured after a period under it: its cranks
    # turn (the PID reaches it in ~20 ms); the state before, stamped 0, shows them still
    assert got[first].state[I_VEL_L] > 3.0 and got[first].state[I_VEL_R] > 3.0, got[first].state[I_VEL_L:I_VEL_L + 2]
    assert abs(got[first - 1].state[I_VEL_L]) < 1.0
    # and so on: each later state's cranks turn at the command it carries: every one above half of it
    # (the wall-clock emulator starved at load 6 once gave 3.8 of 6), their median within 1.5 rev/s
    later = np.array([m.state[I_VEL_L:I_VEL_L + 2] for m in got[first:first + 5]])
    cmds = np.array([m.action for m in got[first:first + 5]])
    assert np.all(later > 0.5 * cmds), later
    np.testing.assert_allclose(np.median(later, axis=0), np.median(cmds, axis=0), atol=1.5)
