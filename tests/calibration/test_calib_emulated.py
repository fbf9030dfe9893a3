"""The robots' own MJCF calibrated from recordings of their emulated rigs (`hil excite`, then
`hil calibrate --model <robot config>`; docs/calibration.md, "The robots' own MuJoCo models"), and
the hand's bench: its drive effects and the rollout model of its firmware loops."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hilstack.calibration import mjcf_robot as M
from hilstack.configs.schema import ConfigError
from hilstack.drivers.registry import make_driver
from hilstack.sim_backends.shadow_hand.firmware import FirmwareConfig, HandFirmware

ROOT = Path(__file__).resolve().parents[2]

try:
    M._sysid()
    HAVE_SYSID = True
except M.SysidNotAvailable:
    HAVE_SYSID = False
needs_sysid = pytest.mark.skipif(not HAVE_SYSID, reason="mujoco.sysid not installed (pip install hilstack[calib])")


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


def _excite(out: Path, *extra: str) -> subprocess.Popen:
    """`hil excite` on the emulated WidowX rig: the real driver over a pty to the bus emulator process."""
    return subprocess.Popen([sys.executable, "-m", "hilstack", "excite", "arm_widowx_emulated", "--out", str(out),
                             "--seconds", "9", "--period", "0.05", "--seed", "3", *extra],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@needs_sysid
def test_emulated_rig_recording_names_the_injected_delay_and_a_clean_rig_gets_none(tmp_path):
    delayed, clean = tmp_path / "delay.mcap", tmp_path / "clean.mcap"
    procs = [_excite(delayed, "--effect", "input_delay_s=0.05"), _excite(clean)]  # both rigs at once
    for p in procs:
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    kw = dict(horizon_s=0.5, candidates=("joint_frictionloss", "input_delay"), max_rounds=1, max_fit_blocks=4,
              progress=False)
    rep = M.run_mjcf_calibration(delayed, "widowx", tmp_path / "cal_delay", **kw)
    assert rep["effects"] == ["input_delay"], rep["rounds"]
    assert abs(rep["values"]["input_delay"][0] - 0.05) < 0.015, rep["values"]
    assert rep["ratio"] <= 0.5, rep["ratio"]
    assert (tmp_path / "cal_delay" / "calibrated.xml").exists()
    rep0 = M.run_mjcf_calibration(clean, "widowx", tmp_path / "cal_clean", **{**kw, "candidates": ("input_delay",)})
    assert "input_delay" not in rep0["effects"], rep0["rounds"]


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
