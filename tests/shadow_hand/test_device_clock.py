"""The hand's own clock (HAND_STATUS.t_fw_ms, 1 ms firmware ticks, 16 bits): unwrapped by the
driver into Observation.device_t_s, recorded as RobotState.device_t_s, and used by calibration so
that a reading that reached the host late (stale on the host, still ok=False) does not split a
recording whose device stamps are continuous."""

from __future__ import annotations

import can
import numpy as np

from hilstack.drivers.shadow_hand.config import ACTUATED_JOINTS, JOINT_NAMES, ShadowHandParams
from hilstack.drivers.shadow_hand.driver import ShadowHandDriver
from hilstack.drivers.shadow_hand.protocol import FW_CLOCK_MODULUS, encode_telemetry, unwrap_fw_clock


def test_unwrap_continues_the_firmware_clock_across_its_16_bit_wrap():
    raws = [65500, 65520, 4, 24, 65535, 0, 20]
    total, last, out = 0, None, []
    for r in raws:
        total = unwrap_fw_clock(last, r, total)
        last = r
        out.append(total)
    assert out == [0, 20, 40, 60, 60 + 65511, 60 + 65512, 60 + 65532]
    assert FW_CLOCK_MODULUS == 65536


def test_driver_reports_the_hand_clock_of_each_cycle_across_the_wrap():
    """Telemetry cycles fed to the driver's reader (as off the bus): device_t_s advances by the
    firmware ticks between cycles, through the 65,535 -> 0 wrap; the host stamp is not used."""
    drv = ShadowHandDriver(ShadowHandParams())
    drv.inputs.start(0.0)
    q, qd, eff = np.zeros(len(JOINT_NAMES)), np.zeros(len(JOINT_NAMES)), np.zeros(len(ACTUATED_JOINTS))
    seen = []
    for k, t_fw in enumerate([65490, 65510, 65530, 14, 34]):
        for mid, data in encode_telemetry(q, qd, eff, mode=2, faults=0, motor_fault_mask=0, cycle=k,
                                          rx_error_count=0, t_fw_ms=t_fw):
            drv._handle(can.Message(arbitration_id=mid, data=data, is_extended_id=False), now=100.0 + 0.5 * k)
        obs = drv._read()
        assert obs.extras["t_fw_ms"] == t_fw
        seen.append(obs.device_t_s)
    np.testing.assert_allclose(np.diff(seen), 0.020, atol=1e-12)  # 20 ticks per cycle, host gaps 0.5 s
    assert seen[0] == 0.0


def test_late_readings_keep_the_recording_whole_on_the_hand_clock(tmp_path):
    """The real driver over SLCAN to the emulator process. Telemetry every 0.2 s, read every 0.15 s
    with the 0.1 s deadline: about a third of the cycles reach the caller older than the deadline
    (the host late, as a loaded machine makes it). Those readings stay ok=False with
    stale_telemetry (safety unchanged); the recording marks them late, and on the hand's clock the
    recording is one episode whose device stamps step by one telemetry period, while on the host's
    clock the late readings cut it into pieces (too short to keep, at this rate)."""
    from hilstack.bus.recording import iter_messages
    from hilstack.bus.schemas import RobotState
    from hilstack.calibration.data import load_episodes
    from hilstack.calibration.robot_rig import record_excitation
    from hilstack.configs.schema import load_robot
    from hilstack.learning.recordings import episodes_from_mcap

    cfg = load_robot("shadow_hand", backend="emulated",
                     params={"transport": "slcan", "telemetry_hz": 5.0, "telemetry_deadline_s": 0.1,
                             "emulator": {"balls": False}})
    path = record_excitation(tmp_path / "late.mcap", duration_s=4.5, seed=3, robot=cfg, period_s=0.15)
    states = [m.msg for m in iter_messages(path) if isinstance(m.msg, RobotState)]
    late = [m for m in states if m.health.get("late")]
    assert len(late) >= 3, f"only {len(late)} late readings of {len(states)}"
    assert all(not m.ok for m in late)  # still not ok: the driver's verdict for control is kept
    assert all(m.device_t_s >= 0 for m in states)

    rec = load_episodes(path)
    assert len(rec) == 1 and rec[0].meta["clock"] == "device"
    dev = rec[0].t_s
    steps = np.diff(dev)
    # continuous: each kept reading is the next telemetry cycle, 0.2 s of the hand's clock later (the
    # emulator's wall-clock pacing moves a cycle by a tick or two; a slip gives up time, never adds it).
    # A host stalled past a whole cycle (load 6: two xdist workers beside two experiments) never read
    # that cycle's frame: the next step is two periods, still on the hand's telemetry grid
    cycles = np.round(steps / 0.2)
    assert np.all(cycles >= 1) and np.all(np.abs(steps - 0.2 * cycles) < 0.05), steps
    assert np.mean(cycles == 1) >= 0.75, steps
    # every distinct cycle is kept, the late ones too
    assert rec[0].n == len({m.device_t_s for m in states})
    host = episodes_from_mcap(path, normalize=False, clock="host")
    # on the host's clock each late reading ends a segment (and short ones are dropped)
    assert len(host) > 1 or sum(len(e.times) for e in host) < rec[0].n / 2


def test_only_readings_marked_late_keep_their_episode_and_only_on_the_device_clock(tmp_path):
    """The loader's rule on its own: a not-ok reading splits the episode unless its recorder marked
    it late (a WidowX stale reading, whose other servos did not answer, is not marked), and only on
    the device clock; a late reading with a non-finite state still splits."""
    from hilstack.bus import keys
    from hilstack.bus.recording import McapLog
    from hilstack.bus.schemas import RobotState
    from hilstack.learning.recordings import episodes_from_mcap

    def write(name, bad_health, bad_state=1.0):
        path = tmp_path / f"{name}.mcap"
        with McapLog(path) as log:
            for k in range(12):
                bad = k == 6
                log.write(keys.state("rig", "arm"),
                          RobotState(robot="arm", t_s=0.05 * k + (0.04 if bad else 0.0), state=[bad_state if bad else 0.1 * k],
                                     action=[] if k == 0 else [0.0], seq=k + 1, ok=not bad, device_t_s=0.02 * k,
                                     health=bad_health if bad else {}))
        return path

    late = write("late", {"late": True})
    assert [len(e.times) for e in episodes_from_mcap(late, normalize=False, clock="device")] == [12]
    assert [len(e.times) for e in episodes_from_mcap(late, normalize=False, clock="host")] == [6, 5]
    unmarked = write("unmarked", {})
    assert [len(e.times) for e in episodes_from_mcap(unmarked, normalize=False, clock="device")] == [6, 5]
    nan = write("nan", {"late": True}, bad_state=float("nan"))
    assert [len(e.times) for e in episodes_from_mcap(nan, normalize=False, clock="device")] == [6, 5]
