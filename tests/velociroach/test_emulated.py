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

from drivers.base import Lifecycle, LinkError
from drivers.velociroach.config import STATE_NAMES, VelociRoachParams
from drivers.velociroach.driver import VelociRoachDriver
from drivers.velociroach.link import addr64, xbee_tx64
from drivers.velociroach.mavlink import BASE_COMPID, BASE_SYSID, MavEncoder

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
        assert h.ok and h.last_heartbeat_s is not None and h.last_heartbeat_s < 2.0

        # command -> the 1 kHz PID makes the cranks track it
        target = np.array([6.0, 6.0])
        last_write = [0.0]

        def drive():
            drv.write(target)
            last_write[0] = time.monotonic()
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
        assert drv.health().latency_s is not None and drv.health().latency_s < 0.1

        # PID gains: set, read back
        assert drv.set_pid_gains(0.06, 1.2, 0.0) == pytest.approx((0.06, 1.2, 0.0), rel=1e-6)
        assert drv.get_pid_gains() == pytest.approx((0.06, 1.2, 0.0), rel=1e-6)

        # silence: the firmware's watchdog stops the motors 500 ms after the last command
        t_last = last_write[0]
        obs = wait_for(lambda: (o := drv.read()).flags["watchdog"] and o, 2.0, "the watchdog fault bit")
        tripped_after_s = obs.t_s - t_last
        assert 0.45 <= tripped_after_s <= 0.8, tripped_after_s
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

        # the emulator process dies (device unplugged): LinkError quickly, never a hang
        drv._proc.kill()
        t0 = time.monotonic()
        with pytest.raises(LinkError, match="unplugged"):
            wait_for(lambda: drv.read() is None, 2.0, "a LinkError")
        assert time.monotonic() - t0 < 1.5
        assert drv.health().ok is False
        assert drv.lifecycle is Lifecycle.UNCONFIGURED and "unplugged" in drv.last_error


def test_radio_silence_shows_in_health_and_the_watchdog_stops_the_robot():
    drv = make(emulator={"silence_after_s": 0.5})
    with drv:
        cmd = np.array([9.0, 9.0])

        def drive():
            drv.write(cmd)  # keeps commanding through the outage: nothing arrives
            drv.tick()

        wait_for(lambda: drv.read().state[I_X] > 0.05, 3.0, "the robot to move", step=drive)
        h = wait_for(lambda: (h := drv.health()).ok is False and h, 3.0, "health to report the outage", step=drive)
        wait_for(lambda: drv.health().link_quality < 0.05, 2.0, "link quality to drop", step=drive)
        t0 = time.monotonic()
        obs = drv.read()
        assert time.monotonic() - t0 < drv.spec.period_s and obs.ok is False
        assert not obs.flags["telemetry_fresh"]
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
        [sys.executable, "-m", "tools.cli", "drive", "velociroach", "--backend", "emulated",
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
