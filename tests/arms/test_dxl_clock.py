"""The servos' own clock (Realtime Tick, address 120): served by the firmware model, decoded and
unwrapped by the driver, recorded as RobotState.device_t_s and used by calibration as the sample time."""

from __future__ import annotations

import numpy as np

from hilstack.drivers.dynamixel.control_table import REALTIME_TICK_MODULUS, control_table, unwrap_tick
from hilstack.drivers.registry import make_driver
from hilstack.sim_backends.dynamixel.firmware import Servo


def test_unwrap_continues_across_the_wrap():
    raws = [32700, 32760, 5, 40, 32767, 0, 1]
    total, last, out = 0, None, []
    for r in raws:
        total = unwrap_tick(last, r, total)
        last = r
        out.append(total)
    assert out == [0, 60, 73, 108, 108 + 32727, 108 + 32728, 108 + 32729]


def test_firmware_serves_its_clock_in_ms_wrapping_after_32767():
    s = Servo(1)
    addr = control_table()["Realtime Tick"].address
    for _ in range(7):
        s.tick(0.0, 0.0)
    assert int.from_bytes(s.read(addr, 2)[1], "little") == 7
    s._clock_s = 32.766  # as after 32.766 s of ticks
    seen = []
    for _ in range(4):
        s.tick(0.0, 0.0)
        seen.append(int.from_bytes(s.read(addr, 2)[1], "little"))
    assert seen == [32767, 0, 1, 2]
    assert max(seen) < REALTIME_TICK_MODULUS


def test_sim_driver_stamps_readings_with_the_servo_clock_across_a_wrap():
    """Lockstep sim bench (the real driver over the in-process bus): the device time of each reading
    advances by exactly one control period, also where the servos' 15-bit tick wraps."""
    d = make_driver("widowx", backend="sim", bus_name="t_devclock")
    with d:
        o0 = d.read()
        assert o0.device_t_s is not None
        for s in d.world.servos.values():
            s._clock_s = 32.70  # as after 32.7 s of running: the next ticks cross 32,767 ms
        d.tick()
        o1 = d.read()
        dev = [o1.device_t_s]
        raw = [d._tick_raw[0]]
        for _ in range(8):
            d.tick()
            obs = d.read()
            dev.append(obs.device_t_s)
            raw.append(d._tick_raw[0])
        steps = np.diff(dev)
        np.testing.assert_allclose(steps, d.spec.period_s, atol=1e-9)
        assert any(b < a for a, b in zip(raw, raw[1:], strict=False))  # the register did wrap
        assert o1.device_t_s > o0.device_t_s  # the clock moved forward, not back


def test_calibration_uses_the_device_clock_and_keeps_host_stamps(tmp_path):
    """A recording whose host stamps jitter but whose device clock is exact: calibration's episodes
    are on the device clock; the learning loader keeps the host stamps (default, and in meta)."""
    from hilstack.bus import keys
    from hilstack.bus.recording import McapLog
    from hilstack.bus.schemas import NO_DEVICE_CLOCK, RobotState
    from hilstack.calibration.data import load_episodes
    from hilstack.learning.recordings import episodes_from_mcap

    rng = np.random.default_rng(0)
    n, period = 60, 0.02
    dev = np.arange(n) * period
    host = dev + 0.004 + rng.uniform(0, 0.02, n)  # stamped when the read returned: late and jittery
    host = np.maximum.accumulate(host) + np.arange(n) * 1e-6
    x = np.sin(dev * 3.0)

    def write(path, device):
        with McapLog(path) as log:
            for k in range(n):
                log.write(keys.state("rig", "arm"),
                          RobotState(robot="arm", t_s=float(host[k]), state=[float(x[k])],
                                     action=[] if k == 0 else [float(np.cos(dev[k]))], seq=k + 1,
                                     device_t_s=float(dev[k]) if device else NO_DEVICE_CLOCK))
        return path

    rec = load_episodes(write(tmp_path / "dev.mcap", True))
    assert rec[0].meta["clock"] == "device"
    np.testing.assert_allclose(rec[0].t_s, dev)
    ep = episodes_from_mcap(tmp_path / "dev.mcap", normalize=False)[0]
    np.testing.assert_allclose(ep.times, host)  # learning's default: the host stamps, as before
    ep = episodes_from_mcap(tmp_path / "dev.mcap", normalize=False, clock="device")[0]
    np.testing.assert_allclose(ep.meta["host_times"], host)
    rec = load_episodes(write(tmp_path / "host.mcap", False))  # no device clock: the host's stamps
    assert rec[0].meta["clock"] == "host"
    np.testing.assert_allclose(rec[0].t_s, host)
