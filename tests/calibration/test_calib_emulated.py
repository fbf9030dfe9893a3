"""The robots' own MJCF calibrated from recordings of their emulated rigs (`hil excite`, then
`hil calibrate --model <robot config>`; docs/calibration.md, "The robots' own MuJoCo models"), and
the hand's bench: its drive effects and the rollout model of its firmware loops."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilstack.calibration import mjcf_robot as M
from hilstack.calibration.data import load_episodes
from hilstack.configs.schema import ConfigError
from hilstack.drivers.registry import make_driver
from hilstack.sim_backends.shadow_hand.firmware import FirmwareConfig, HandFirmware
from tests.calibration.sysid import needs_sysid

# ----------------------------------------------------------------------------- the hand's drive effects


def _firmware(**effects) -> HandFirmware:
    n = 2
    fw = HandFirmware(FirmwareConfig(kp_nm_per_rad=np.full(n, 5.0), kd_nms_per_rad=np.zeros(n),
                                     ki_nm_per_rad_s=np.zeros(n), torque_limit_nm=np.full(n, 4.0),
                                     joint_low_rad=np.full(n, -1.0), joint_high_rad=np.full(n, 1.0), **effects))
    return fw


def test_hand_drive_friction_opposes_motion_and_leaves_the_reported_effort():
    plain, rough = _firmware(), _firmware(friction_nm=0.2, damping_nm_s=0.5)
    for fw in (plain, rough):
        fw.set_targets(0, np.array([0.1, -0.1]), 0.0)
    qd = np.array([1.0, -1.0])
    tau_plain = plain.tick(0.001, np.zeros(2), qd)
    tau_rough = rough.tick(0.001, np.zeros(2), qd)
    # moving +: 0.2 N·m dry + 0.5 N·m·s/rad × 1 rad/s taken off the joint; moving −: given back
    assert tau_rough == pytest.approx(tau_plain - np.array([0.7, -0.7]))
    assert rough.effort_nm == pytest.approx(plain.effort_nm)  # the motor's effort is what is reported


def test_hand_target_delay_holds_the_old_targets_for_the_delay():
    fw = _firmware(input_delay_s=0.01)
    fw.set_targets(0, np.array([0.2, 0.2]), now_s=0.0)
    early = [fw.tick(0.001 * (k + 1), np.zeros(2), np.zeros(2)) for k in range(9)]
    assert all(np.allclose(t, 0.0) for t in early)  # 9 ms: still the old targets (0)
    assert fw.tick(0.011, np.zeros(2), np.zeros(2)) == pytest.approx([1.0, 1.0])  # then kp·0.2
    fw.set_estop(True)  # an e-stop is never delayed
    assert fw.tick(0.012, np.zeros(2), np.zeros(2)) == pytest.approx([0.0, 0.0])


@pytest.mark.parametrize("bad, match", [({"joint_frictoin_nm": 0.1}, "unknown effect 'joint_frictoin_nm'"),
                                        ({"input_delay_s": -0.01}, "outside"),
                                        ({"joint_friction_nm": float("nan")}, "finite")])
def test_hand_bad_effects_are_a_config_error_naming_the_field(bad, match):
    with pytest.raises(ConfigError, match=match) as e:
        make_driver("shadow_hand", backend="sim", sim={"effects": bad})
    assert "params.sim.effects" in str(e.value)


def test_hand_rollout_model_is_the_firmware():
    """The rollout model of the hand's 20 position loops (mujoco.pid actuator plugins) reproduces the
    firmware-driven sim from the same state (a wrong gain, clamp or sign fails this)."""
    import mujoco

    from hilstack.drivers.shadow_hand.config import to_joint_rad

    d = make_driver("shadow_hand", backend="sim", sim={"balls": False}, period_s=0.02)
    bench = M.Bench.from_layout(d.calibration_bench(d.params))
    m = M.servo_spec(bench).compile()
    with d:
        home = np.asarray(d.spec.home_action)
        for k in range(25):
            d.write(home + 0.3 * np.sin(0.4 * k))
            d.tick()
        sm, sd = d.model, d.data
        md = mujoco.MjData(m)
        for j in range(24):
            nm = sm.joint(j).name
            md.joint(nm).qpos[:] = sd.joint(nm).qpos
            md.joint(nm).qvel[:] = sd.joint(nm).qvel
        acts = [m.actuator(sm.actuator(i).name).id for i in range(20)]
        md.act[[m.actuator_actadr[i] for i in acts]] = d.firmware.integral_rad_s
        for k in range(10):
            md.ctrl[acts] = to_joint_rad(np.asarray(d.write(home + 0.3 * np.sin(0.4 * (25 + k)))))
            for _ in range(20):
                mujoco.mj_step(m, md)
            d.tick()
            assert np.max(np.abs(md.qpos[:24] - sd.qpos[:24])) < 1e-8, k


# ----------------------------------------------------------------------------- WidowX, emulated rig, end to end

#: 10.5 s of the emulated WidowX rig (the real driver over a pty to the bus emulator process, on the
#: wall clock, 50 ms periods), windows without a stall cut from `hil excite arm_widowx_emulated
#: --seconds 80 --period 0.05 --seed 0 [--effect input_delay_s=0.03]` (33.5-44 s and 24-34.5 s;
#: docs/calibration.md, "Results on the emulated rigs"). Recorded, not generated here: on this loaded
#: 2-core machine the real-time emulator stalls the pty (write timeouts) at random.
DATA = Path(__file__).resolve().parents[1] / "data" / "calibration"  # real emulated-rig recordings (.gitignore keeps tests/data/**)
KW = dict(horizon_s=0.5, max_rounds=1, max_fit_blocks=4, progress=False)


@needs_sysid
def test_emulated_rig_recording_names_the_injected_delay_and_the_clean_rig_only_its_link(tmp_path):
    rep = M.run_mjcf_calibration(DATA / "widowx_emulated_delay30ms.mcap", "widowx", tmp_path / "cal",
                                 candidates=("joint_frictionloss", "input_delay"), **KW)
    assert rep["effects"] == ["input_delay"], rep["rounds"]
    assert rep["ratio"] <= 0.5, rep["ratio"]
    assert (tmp_path / "cal" / "calibrated.xml").exists()
    # the clean rig: no injected delay; what it may show is its link's own latency (pty, host stamps)
    rep0 = M.run_mjcf_calibration(DATA / "widowx_emulated_clean.mcap", "widowx", tmp_path / "cal0",
                                  candidates=("input_delay",), **KW)
    link = rep0["values"].get("input_delay", [0.0])[0]
    assert link < 0.015, rep0["values"]
    # the injected 30 ms on top of the link
    assert abs(rep["values"]["input_delay"][0] - link - 0.03) < 0.008, (rep["values"], link)


def test_excite_refuses_bad_input_in_one_line(tmp_path):
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    runner = CliRunner()
    res = runner.invoke(app, ["excite", "arm_widowx_emulated", "--out", str(tmp_path / "r.mcap"),
                              "--effect", "input_delay_s"])
    assert res.exit_code == 2 and "expected KEY=VALUE" in res.output
    res = runner.invoke(app, ["excite", "arm_widowx_emulated", "--out", str(tmp_path / "r.mcap"), "--robot", "leg"])
    assert res.exit_code == 2 and "has robots" in res.output
    (tmp_path / "r.mcap").write_bytes(b"keep")
    res = runner.invoke(app, ["excite", "arm_widowx_sim", "--out", str(tmp_path / "r.mcap")])
    assert res.exit_code == 2 and "exists" in res.output
    assert (tmp_path / "r.mcap").read_bytes() == b"keep"
    res = runner.invoke(app, ["excite", "arm_widowx_sim", "--out", str(tmp_path / "s.mcap"), "--seconds", "1",
                              "--effect", "backlash_rad=0.01"])
    assert res.exit_code == 2 and "unknown effect 'backlash_rad'" in res.output, res.output
    assert not (tmp_path / "s.mcap").exists()
    # and a good one: the spec and one state per period, the applied actions, within the arm's limits
    res = runner.invoke(app, ["excite", "arm_widowx_sim", "--out", str(tmp_path / "s.mcap"), "--seconds", "1",
                              "--period", "0.05", "--effect", "joint_friction_nm=0.2", "--json"])
    assert res.exit_code == 0, res.output
    (ep,) = load_episodes(tmp_path / "s.mcap")
    assert ep.n == 21 and ep.states.shape[1] == 18 and ep.actions.shape[1] == 6
    assert np.all(np.abs(ep.actions) <= 1.0 + 1e-9) and np.ptp(ep.actions, axis=0).min() > 0


def test_no_block_spans_a_stall_of_a_wall_clock_rig():
    """A period longer than 2 median periods (the emulator gave up time it could not catch up
    with) starts new blocks after it; remove the rule and a block spans the stall."""
    from hilstack.calibration.data import Recording

    t = np.arange(400) * 0.05
    t[205:] += 0.3  # a 0.35 s period before sample 205
    states = np.zeros((400, 3))
    rec = Recording(name="r", t_s=t, u=np.zeros(400), x=np.zeros(400), states=states, actions=np.zeros((400, 1)))
    bench = M.Bench(spec=None, joints=["j"], loops={}, q=[0], qd=[1], current=[2])
    blocks = M.make_blocks([rec], bench, 0.001, horizon_s=0.5)
    assert blocks.spans, "no blocks"
    for _, s, h in blocks.spans:
        assert not (s < 205 <= s + h - 1), (s, h)  # no block holds both sides of the stall
    assert any(s >= 205 for _, s, _ in blocks.spans) and any(s + h <= 205 for _, s, h in blocks.spans)
