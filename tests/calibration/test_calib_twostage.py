"""Two-stage calibration of a robot's own MJCF (`hil calibrate --model <robot config> --base CLEAN`;
docs/calibration.md, "Two-stage calibration"): a rig whose clean recording already differs from the
MJCF (here a standing 20 ms goal delay, as the emulated WidowX rig's link has one of its own) is
calibrated clean first; the effect recording is then judged against that clean fit. Without the clean
stage the rig's own lag is what round 1 names on the effect recording (asserted below)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from hilstack.calibration import mjcf_robot as M
from hilstack.calibration.data import DataError
from hilstack.calibration.robot_rig import record_excitation
from tests.calibration.sysid import needs_sysid

pytestmark = needs_sysid

RIG_LAG_S = 0.02  # what the rig has, clean, that the MJCF lacks
KW = dict(progress=False, candidates=("joint_frictionloss", "input_delay"), max_rounds=1, max_fit_blocks=4, horizon_s=1.0)


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    return str(tmp_path_factory.mktemp("twostage"))


@functools.cache
def _rec(tmp: str, friction_nm: float, seed: int) -> str:
    path = f"{tmp}/rig_f{friction_nm:g}_s{seed}.mcap"
    eff = {"input_delay_s": RIG_LAG_S, **({"joint_friction_nm": friction_nm} if friction_nm else {})}
    record_excitation(path, duration_s=24.0, seed=seed, effects=eff, period_s=0.05)
    return path


@functools.cache
def _clean(tmp: str) -> dict:
    return M.run_mjcf_calibration(_rec(tmp, 0.0, 0), "widowx", f"{tmp}/clean", **{**KW, "candidates": ("input_delay",)})


def test_clean_stage_fits_the_rigs_own_lag(tmp):
    rep = _clean(tmp)
    assert rep["effects"] == ["input_delay"], rep["rounds"]
    assert abs(rep["values"]["input_delay"][0] - RIG_LAG_S) < 0.004, rep["values"]


def test_effect_is_named_against_the_clean_fit_and_not_without_it(tmp):
    clean = _clean(tmp)
    rec = _rec(tmp, 0.3, 1)
    # one stage (the MJCF as shipped): the rig's own lag outscores the injected friction
    one = M.run_mjcf_calibration(rec, "widowx", f"{tmp}/one", **KW)
    first = {c["added"]: c["evidence"]["gain"] for c in one["rounds"][0]}
    assert one["effects"] == ["input_delay"] and first["input_delay"] > first["joint_frictionloss"], one["rounds"]
    # two stages: judged against the clean fit, the friction is what is missing
    two = M.run_mjcf_calibration(rec, "widowx", f"{tmp}/two", base=f"{tmp}/clean", **KW)
    assert two["effects"] == ["joint_frictionloss"], two["rounds"]
    v = np.array(two["values"]["joint_frictionloss"])
    assert np.all(np.abs(v - 0.4) < 0.08), v  # 0.1 N·m in the MJCF + 0.3 in each gearbox
    assert two["ratio"] <= 0.5, (two["before_multi_step_nrmse"], two["after_multi_step_nrmse"])
    # the written MJCF keeps the base's delay (it was not refitted) beside the new friction
    bench = M.bench_of("widowx", base=two["calibrated_mjcf"])
    assert bench.input_delay_s == pytest.approx(clean["values"]["input_delay"][0], rel=1e-5)
    assert two["base"].endswith("clean/calibrated.xml")


def test_bad_base_is_a_one_line_error(tmp, tmp_path):
    with pytest.raises(DataError, match="no calibrated.xml in that directory"):
        M.run_mjcf_calibration(_rec(tmp, 0.0, 0), "widowx", tmp_path / "o", base=tmp_path, **KW)
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody/></mujoco>")
    with pytest.raises(DataError, match="no joint named 'waist'"):
        M.bench_of("widowx", base=bad)
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    res = CliRunner().invoke(app, ["calibrate", "--data", str(bad), "--model", "axis", "--base", str(tmp_path)])
    assert res.exit_code == 2 and "--base and --current are for --model <robot config>" in res.output, res.output
