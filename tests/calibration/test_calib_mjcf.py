"""Calibrating the WidowX's own MJCF against recordings of a bench whose servos carry an effect
the MuJoCo model lacks (calibration/mjcf_robot.py, calibration/robot_rig.py, the firmware's
``effects``). Short recordings (tens of seconds of sim time), few fit blocks."""

from __future__ import annotations

import functools
import json
import os

import numpy as np
import pytest

from hilstack.calibration import mjcf_robot as M  # an import error here is a failure, never a skip
from hilstack.calibration.data import DataError, load_episodes
from hilstack.calibration.robot_rig import record_excitation
from hilstack.drivers.dynamixel.control_table import OPERATING_MODES
from hilstack.drivers.registry import make_driver
from hilstack.sim_backends.dynamixel.firmware import Servo, ServoPhysics, effect_fields
from hilstack.sim_backends.widowx import emulator
from tests.calibration.sysid import needs_sysid

# ----------------------------------------------------------------------------- the bench's effects


def _velocity_servo(**effects) -> Servo:
    s = Servo(1, physics=ServoPhysics(**effect_fields(effects)))
    s.set("Operating Mode", OPERATING_MODES["velocity"])
    s.set("Torque Enable", 1)
    return s


def _write_goal_velocity(s: Servo, counts: int) -> None:
    it = s.table["Goal Velocity"]
    assert s.write(it.address, it.encode(counts)) == 0


def test_gearbox_friction_opposes_motion_and_leaves_the_motor_current():
    plain, rough = _velocity_servo(), _velocity_servo(joint_friction_nm=0.4)
    tau_plain = plain.tick(0.0, 0.5)
    tau_rough = rough.tick(0.0, 0.5)
    assert tau_rough == pytest.approx(tau_plain - 0.4)  # moving +: friction takes 0.4 N·m off the shaft
    assert plain._present[2] == pytest.approx(rough._present[2])  # the current is the motor's, before losses
    assert rough.tick(0.0, -0.5) == pytest.approx(plain.tick(0.0, -0.5) + 0.4)


def test_input_delay_holds_the_old_goal_for_the_delay():
    s = _velocity_servo(input_delay_s=0.01)
    ref = _velocity_servo()
    _write_goal_velocity(s, 40)
    _write_goal_velocity(ref, 40)
    assert s.get("Goal Velocity") == 40  # the register reads back at once
    early = [s.tick(0.0, 0.0) for _ in range(9)]
    assert all(abs(t) < 1e-9 for t in early)  # 9 ms: still the old goal (0)
    for _ in range(3):
        s.tick(0.0, 0.0)
    assert ref.tick(0.0, 0.0) > 0 and s._present[2] > 0  # past 10 ms: the new goal acts


@pytest.mark.parametrize("bad, match", [({"joint_frictoin_nm": 0.1}, "unknown effect 'joint_frictoin_nm'"),
                                        ({"input_delay_s": -0.01}, "input_delay_s: -0.01 is outside"),
                                        ({"joint_friction_nm": float("nan")}, "joint_friction_nm: nan is outside"),
                                        ({"joint_damping_nm_s": "x"}, "not a number")])
def test_bad_effects_are_refused_by_name(bad, match):
    with pytest.raises(ValueError, match=match):
        effect_fields(bad)


def test_emulator_refuses_bad_effects_in_one_line(capsys):
    assert emulator.main(["--print-pty", "--config", json.dumps({"effects": {"backlash_rad": 0.01}})]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown effect 'backlash_rad'" in err[0]


def test_recording_refuses_to_overwrite(tmp_path):
    p = tmp_path / "r.mcap"
    record_excitation(p, duration_s=0.5, seed=0)
    size = p.stat().st_size
    with pytest.raises(FileExistsError):
        record_excitation(p, duration_s=0.5, seed=1)
    assert p.stat().st_size == size


# ----------------------------------------------------------------------------- calibration


@functools.cache
def _recording(tmp: str, effects: tuple, seed: int, duration_s: float) -> str:
    path = f"{tmp}/rec_{'_'.join(f'{k}{v}' for k, v in effects) or 'clean'}_{seed}_{duration_s:g}.mcap"
    record_excitation(path, duration_s=duration_s, seed=seed, effects=dict(effects))
    return path


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    return str(tmp_path_factory.mktemp("mjcf"))


def _bench(**sim):
    d = make_driver("widowx", backend="sim", sim=sim) if sim else make_driver("widowx", backend="sim")
    return M.Bench.from_layout(d.calibration_bench(d.params))


def _calibrate(tmp, effects, out, seed=0):
    return _calibrated(tmp, tuple(sorted(effects.items())), out, seed)


@functools.cache
def _calibrated(tmp, effects, out, seed):
    rec = _recording(tmp, effects, seed, 32.0)
    return M.run_mjcf_calibration(rec, "widowx", f"{tmp}/{out}", seed=seed, progress=False,
                                  candidates=("joint_frictionloss", "input_delay"), max_rounds=1, max_fit_blocks=4)


@needs_sysid
def test_friction_is_named_identified_with_intervals_and_halves_the_heldout_error(tmp):
    rep = _calibrate(tmp, {"joint_friction_nm": 0.3}, "fric")
    assert rep["effects"] == ["joint_frictionloss"]
    first = {c["added"]: c["evidence"] for c in rep["rounds"][0]}
    assert first["joint_frictionloss"]["level"] in ("strong", "moderate")
    assert first["input_delay"]["gain"] < first["joint_frictionloss"]["gain"]
    v, ci = np.array(rep["values"]["joint_frictionloss"]), np.array(rep["intervals_95"]["joint_frictionloss"])
    # the bench: 0.1 N·m in the MJCF + 0.3 N·m in each gearbox
    assert np.all(np.abs(v - 0.4) < 0.06), v
    assert np.all(np.isfinite(ci)) and np.all(ci < 0.05)
    assert rep["ratio"] <= 0.5, rep["ratio"]
    # the calibrated MJCF is the backend's model with the identified values; the sim loads it
    d = make_driver("widowx", backend="sim", bus_name="t_mjcf_load", sim={"mjcf": rep["calibrated_mjcf"]})
    with d:
        fl = [float(d.world.model.dof_frictionloss[d.world.model.joint(j).dofadr[0]]) for j in rep["joints"]]
    assert fl == pytest.approx(list(v), rel=1e-5)  # the MJCF keeps 6 digits


@needs_sysid
def test_calibrated_mjcf_predicts_a_new_recording_better(tmp):
    rep = _calibrate(tmp, {"joint_friction_nm": 0.3}, "fric")
    new = load_episodes(_recording(tmp, (("joint_friction_nm", 0.3),), 7, 24.0))
    before = M.evaluate(_bench(), new)
    after = M.evaluate(_bench(mjcf=rep["calibrated_mjcf"]), new)
    assert after < 0.6 * before, (before, after)


@needs_sysid
def test_input_delay_is_named_and_its_value_recovered(tmp):
    rep = _calibrate(tmp, {"input_delay_s": 0.03}, "delay")
    assert rep["effects"] == ["input_delay"]
    (d,), (h,) = rep["values"]["input_delay"], rep["intervals_95"]["input_delay"]
    assert abs(d - 0.03) < 0.006 and h < 0.01, (d, h)
    assert rep["ratio"] <= 0.5
    # the written MJCF carries the delay; the bench's servos apply it
    drv = make_driver("widowx", backend="sim", bus_name="t_mjcf_delay", sim={"mjcf": rep["calibrated_mjcf"]})
    with drv:
        phys = [drv.world.servos[i].phys.input_delay_s for i in drv.ids.values()]
    assert phys == pytest.approx([d] * 6, rel=1e-5)  # MuJoCo writes the numeric with 6 significant digits


@needs_sysid
def test_clean_bench_gets_no_effect(tmp):
    rep = _calibrate(tmp, {}, "clean")
    assert rep["effects"] == [], rep["rounds"]


def test_bad_mjcf_is_refused_in_one_line(tmp_path):
    bad = tmp_path / "arm.xml"
    bad.write_text("<mujoco><worldbody/></mujoco>")
    with pytest.raises(ValueError, match=r"no joint named 'waist'"):
        make_driver("widowx", backend="sim", bus_name="t_bad_mjcf", sim={"mjcf": str(bad)}).configure()


@needs_sysid
def test_short_recording_and_overwrite_are_refused(tmp):
    rec = _recording(tmp, (), 3, 6.0)
    with pytest.raises(DataError, match="recording too short"):
        M.run_mjcf_calibration(rec, "widowx", f"{tmp}/short", progress=False)
    out = f"{tmp}/exists"
    os.makedirs(out, exist_ok=True)
    open(f"{out}/calibrated.xml", "w").write("keep")
    with pytest.raises(DataError, match="exists"):
        M.run_mjcf_calibration(rec, "widowx", out, progress=False)
    assert open(f"{out}/calibrated.xml").read() == "keep"


@needs_sysid
def test_cli_robot_config_errors_are_one_line(tmp, tmp_path):
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    runner = CliRunner()
    res = runner.invoke(app, ["calibrate", "--model", "configs/robots/widowx.yaml", "--data",
                              str(tmp_path / "none.mcap"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "no such file" in res.output
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "calibrated.xml").write_text("keep")
    res = runner.invoke(app, ["calibrate", "--model", "configs/robots/widowx.yaml", "--data",
                              _recording(tmp, (), 3, 6.0), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "exists (pass --force" in res.output
    assert (tmp_path / "o" / "calibrated.xml").read_text() == "keep"
