"""Config errors name the file, the field and what was expected."""

from __future__ import annotations

import math
import re
import subprocess
import sys

import pytest
import yaml
from pydantic import TypeAdapter, ValidationError

from hilstack.configs.schema import ConfigError, load_rig, load_robot
from hilstack.drivers.registry import make_driver
from tests.helpers import ROOT


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_shipped_configs_load():
    assert load_robot("pointmass").robot == "pointmass"
    rig = load_rig("pointmass_sim")
    assert "pm" in rig.robots and rig.watchdog_periods == 3


def test_unknown_backend_names_file_and_field(tmp_path):
    p = _write(tmp_path, "r.yaml", "robot: pointmass\nbackend: hardware\n")
    with pytest.raises(ConfigError) as e:
        load_robot(p)
    msg = str(e.value)
    assert str(p) in msg and "backend" in msg and "'real', 'emulated' or 'sim'" in msg


def test_bad_robot_param_names_params_field(tmp_path):
    p = _write(tmp_path, "r.yaml", "robot: pointmass\nparams:\n  mass_kg: -1\n")
    with pytest.raises(ConfigError) as e:
        make_driver(load_robot(p))
    assert str(p) in str(e.value) and "params.mass_kg" in str(e.value) and "greater than 0" in str(e.value)
    p = _write(tmp_path, "r2.yaml", "robot: pointmass\nparams:\n  mas_kg: 1\n")
    with pytest.raises(ConfigError, match="params.mas_kg"):
        make_driver(load_robot(p))


def test_unknown_robot_and_missing_backend(tmp_path):
    p = _write(tmp_path, "r.yaml", "robot: teapot\n")
    with pytest.raises(ConfigError, match="unknown robot 'teapot'"):
        make_driver(load_robot(p))
    p = _write(tmp_path, "r.yaml", "robot: pointmass\nbackend: real\n")
    with pytest.raises(ConfigError, match="no 'real' backend"):
        make_driver(load_robot(p))


def test_rig_errors(tmp_path):
    p = _write(tmp_path, "rig.yaml", "name: bad name\nrobots: {}\nbus:\n  endpoint: localhost\n  colour: red\n")
    with pytest.raises(ConfigError) as e:
        load_rig(p)
    msg = str(e.value)
    assert "name" in msg and "bus.endpoint" in msg and "tcp/127.0.0.1:7447" in msg and "bus.colour" in msg


def test_yaml_syntax_error_has_line(tmp_path):
    p = _write(tmp_path, "r.yaml", "robot: [pointmass\n")
    with pytest.raises(ConfigError, match=r"line \d+"):
        load_robot(p)


def test_unknown_config_name_lists_known():
    with pytest.raises(ConfigError, match="pointmass"):
        load_robot("no_such_robot")


# ---------------------------------------------------------------- issue 22, item 11: bounded values
def _hil(args: list[str], timeout_s: float = 120.0) -> subprocess.CompletedProcess:
    """`hil ARGS` in its own process (real signals, real exit codes); killed if it hangs."""
    return subprocess.run([sys.executable, "-m", "hilstack.tools.cli", *args], capture_output=True, text=True,
                          timeout=timeout_s, cwd=ROOT)


def _one_error_line(r: subprocess.CompletedProcess) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip() and " INFO " not in ln and " WARNING " not in ln]
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "Traceback" not in r.stderr and len(lines) == 1, r.stderr
    return lines[0]


#: (robot, params) the review found accepted: each turned a protection off or hung a verb
SWITCHED_OFF = [
    ("velociroach", {"max_leg_accel_rps2": ".inf"}, "max_leg_accel_rps2", "finite"),  # rate limit off: 0 -> ±15
    ("velociroach", {"max_leg_vel_rps": "1e12"}, "max_leg_vel_rps", "less than or equal to 20"),
    ("velociroach", {"period_s": "1.0e9"}, "period_s", "less than or equal to 0.1"),
    ("velociroach", {"telemetry_deadline_s": ".inf"}, "telemetry_deadline_s", "finite"),
    ("velociroach", {"pose_deadline_s": ".nan"}, "pose_deadline_s", "finite"),
    ("velociroach", {"link_timeout_periods": "1000000000000"}, "link_timeout_periods", "less than or equal to 10000"),
    ("velociroach", {"firmware_watchdog_s": ".inf"}, "firmware_watchdog_s", "finite"),
    ("pointmass", {"period_s": "1.0e9"}, "period_s", "less than or equal to 1"),
    ("pointmass", {"physics_dt_s": "1.0e-300"}, "physics_dt_s", "greater than or equal to 0.00001"),
    ("shadow_hand", {"telemetry_deadline_s": ".inf"}, "telemetry_deadline_s", "finite"),
    ("shadow_hand", {"driver_watchdog_s": ".inf"}, "driver_watchdog_s", "finite"),
    ("shadow_hand", {"max_action_rate_per_s": "1.0e9"}, "max_action_rate_per_s", "less than or equal to 20"),
    ("widowx", {"telemetry_stale_s": ".inf"}, "telemetry_stale_s", "finite"),
    ("widowx", {"max_joint_accel_rad_s2": "1.0e12"}, "max_joint_accel_rad_s2", "less than or equal to 96"),
    ("sawyer", {"joint_states_stale_s": ".inf"}, "joint_states_stale_s", "finite"),
    ("sawyer", {"max_joint_vel_rad_s": "1.0e3"}, "max_joint_vel_rad_s", "less than or equal to 4.545"),
    ("camera", {"fail_after_s": ".inf"}, "fail_after_s", "finite"),
    ("reset_arm", {"state_deadline_s": ".inf"}, "state_deadline_s", "finite"),
    ("reset_arm", {"max_joint_rate_rad_s": "1.0e6"}, "max_joint_rate_rad_s", "less than or equal to 2.61"),
    ("mocap", {"stale_after_s": ".inf"}, "stale_after_s", "finite"),
]


@pytest.mark.parametrize(("robot", "params", "field", "why"), SWITCHED_OFF,
                         ids=[f"{r}-{f}" for r, _, f, _ in SWITCHED_OFF])
def test_a_value_that_switches_a_protection_off_is_refused(tmp_path, robot, params, field, why):
    """Item 11: `.inf`, NaN and absurd finite values of every safety parameter are config
    errors naming the file and the field (each robot's real backend: its params class)."""
    body = "".join(f"  {k}: {v}\n" for k, v in params.items())
    backend = "real" if robot in ("mocap", "camera") else "sim"
    p = _write(tmp_path, "r.yaml", f"robot: {robot}\nbackend: {backend}\nparams:\n{body}")
    with pytest.raises(ConfigError) as e:
        make_driver(load_robot(p))
    msg = str(e.value)
    assert f"{p}: params.{field}:" in msg and why in msg, msg


def test_a_deadline_in_periods_is_bounded_as_a_time(tmp_path):
    """1000 periods of 0.1 s: a roach link silent for 100 s still counted as up."""
    p = _write(tmp_path, "r.yaml", "robot: velociroach\nparams: {link_timeout_periods: 1000, period_s: 0.1}\n")
    with pytest.raises(ConfigError, match=rf"{p}: params: link_timeout_periods: 1000 periods of 0.1 s = 100 s, more "):
        make_driver(load_robot(p))
    p = _write(tmp_path, "r.yaml", "robot: velociroach\nparams: {link_timeout_periods: 100, period_s: 0.1}\n")
    make_driver(load_robot(p))


def test_the_rig_watchdog_cannot_be_switched_off(tmp_path):
    for v, why in ((".inf", "finite"), ("1.0e9", "less than or equal to 10"), ("0.1", "greater than or equal to 1")):
        p = _write(tmp_path, "rig.yaml", f"name: r\nrobots: {{pm: {{config: pointmass}}}}\nwatchdog_periods: {v}\n")
        with pytest.raises(ConfigError, match=rf"{p}: watchdog_periods: .*{why}"):
            load_rig(p)


def test_reset_values_are_finite_and_bounded(tmp_path):
    from hilstack.control.reset.config import load_reset

    for reset, fld in (({"robot": "pm", "steps": [{"kind": "teleport", "timeout_s": ".inf"}]}, r"steps\[0\].timeout_s"),
                       ({"robot": "pm", "steps": [{"kind": "teleport", "retries": 10**9}]}, r"steps\[0\].retries"),
                       ({"robot": "pm", "steps": [{"kind": "teleport"}], "state_timeout_s": ".nan"}, "state_timeout_s"),
                       ({"robot": "pm", "steps": [{"kind": "drive_to_start", "params": {"speed": ".nan"}}]},
                        r"steps\[0\].params.speed")):
        text = yaml.safe_dump({"name": "r", "robots": {"pm": {"config": "pointmass"}}, "reset": reset})
        p = _write(tmp_path, "rig.yaml", text.replace("'.inf'", ".inf").replace("'.nan'", ".nan"))
        with pytest.raises(ConfigError, match=rf"{p}: reset.{fld}: "):
            load_reset(load_rig(p))


def test_a_huge_period_is_refused_by_hil_drive_at_once(tmp_path):
    """`period_s: 1e9` hung `hil drive` (one tick of 10⁹ s); now exit 2, one line."""
    p = _write(tmp_path, "r.yaml", "robot: pointmass\nparams:\n  period_s: 1.0e9\n")
    line = _one_error_line(_hil(["drive", str(p), "--seconds", "0.1"], timeout_s=60))
    assert f"{p}: params.period_s:" in line


# the safety parameters: every one carries its bounds and their source (docs/platform.md's table)
SAFETY_NAME = re.compile(r"(period_s|_deadline_s|_stale_s|stale_after_s|fail_after_s|watchdog_s|watchdog_periods|"
                         r"timeout_s|timeout_periods|_rps|_rps2|_rad_s|_rad_s2|_per_s|_m_s|_hz|fps|max_s)$")


def safety_fields():
    from hilstack.tools.config_bounds import config_models

    for model in config_models():
        for name, fi in model.model_fields.items():
            if SAFETY_NAME.search(name):
                yield model, name, fi


def test_every_safety_parameter_is_finite_bounded_and_says_why():
    """Item 11, for every robot and every field added later: a safety parameter (period,
    deadline, watchdog, timeout, rate, velocity or acceleration limit) refuses inf, NaN and
    1e300, and its type names the physical source of its bounds (a shared bounded type)."""
    from hilstack.tools.config_bounds import field_bounds

    checked = []
    for model, name, fi in safety_fields():
        lo, hi, source = field_bounds(fi)
        assert source, f"{model.__name__}.{name}: no Bound (use a shared bounded type of configs/schema.py)"
        assert lo is not None and hi is not None and math.isfinite(lo[1]) and math.isfinite(hi[1]), (name, lo, hi)
        adapter = TypeAdapter(fi.rebuild_annotation())
        for bad in (math.inf, -math.inf, math.nan, 1e300, -1e300):
            with pytest.raises(ValidationError):
                adapter.validate_python(bad)
        checked.append(f"{model.__name__}.{name}")
    assert len(checked) > 40, checked  # every robot's periods, deadlines, watchdogs, rates...
    for must in ("VelociRoachParams.max_leg_accel_rps2", "RigConfig.watchdog_periods",
                 "ShadowHandParams.telemetry_deadline_s", "WidowXParams.max_joint_vel_rad_s",
                 "SawyerParams.joint_states_stale_s", "StepConfig.timeout_s",
                 "PanUnitParams.pan_rate_rad_s"):  # a robot found through the registry (tools/config_bounds.py)
        assert must in checked


def test_no_config_float_accepts_inf_or_nan():
    """Beyond the named safety parameters: no float of any robot, rig or reset config is
    inf or NaN (the shared bases refuse them)."""
    from hilstack.tools.config_bounds import config_models

    for model in config_models():
        assert model.model_config.get("allow_inf_nan") is False, model.__name__


# ---------------------------------------------------------------- issue 22, item 12: malformed shapes
@pytest.mark.parametrize("text", ["- robot: pointmass\n", "just words\n", "42\n", "[1, 2]\n"])
def test_a_top_level_that_is_not_a_mapping_is_one_error(tmp_path, text):
    from hilstack.configs.schema import load_task

    for name, load in (("robot.yaml", load_robot), ("rig.yaml", load_rig), ("task.yaml", load_task)):
        p = _write(tmp_path, name, text)
        with pytest.raises(ConfigError, match=rf"{p}: <root>: expected a mapping .* at top level, got a "):
            load(p)


def test_a_task_has_no_infinite_numbers(tmp_path):
    from hilstack.configs.schema import load_task

    p = _write(tmp_path, "t.yaml", "task: path_following\npath_scale: .inf\nspeeds: {low: 0.5, high: .nan}\n")
    with pytest.raises(ConfigError, match=rf"{p}: path_scale: expected a finite number \(got inf\)"):
        load_task(p)
    with pytest.raises(ConfigError, match=r"speeds.high: expected a finite number"):
        load_task(p)


def test_a_reset_section_of_the_wrong_shape_names_it(tmp_path):
    from hilstack.control.reset.config import load_reset

    p = _write(tmp_path, "rig.yaml", "name: r\nrobots: {pm: {config: pointmass}}\nreset: [teleport]\n")
    with pytest.raises(ConfigError, match=rf"{p}: reset: Input should be a valid dictionary"):
        load_rig(p)
    p = _write(tmp_path, "rig.yaml", "name: r\nrobots: {pm: {config: pointmass}}\nreset: {robot: pm, steps: [{}]}\n")
    with pytest.raises(ConfigError, match=rf"{p}: reset.steps\[0\].kind: Field required"):
        load_reset(load_rig(p))


def test_joint_limits_low_above_high_or_past_the_hardware(tmp_path):
    for lim, why in (("[1.0, -1.0]", "low 1 must be below high -1"),
                     ("[-4.0, 1.0]", "waist: .* leaves the hardware's range"),
                     ("[.nan, 1.0]", "finite"),
                     ("[0.0]", r"waist\[1\]: Field required")):
        p = _write(tmp_path, "wx.yaml", f"robot: widowx\nbackend: sim\nparams:\n  joint_limits_rad: {{waist: {lim}}}\n")
        with pytest.raises(ConfigError, match=rf"{p}: params.joint_limits_rad.*{why}"):
            make_driver(load_robot(p))
    p = _write(tmp_path, "wx.yaml", "robot: widowx\nbackend: sim\nparams:\n  joint_limits_rad: {wrist: [0, 1]}\n")
    with pytest.raises(ConfigError, match=r"params.joint_limits_rad: unknown joint 'wrist'"):
        make_driver(load_robot(p))
    p = _write(tmp_path, "wx.yaml", "robot: widowx\nbackend: sim\nparams:\n  joint_limits_rad: {waist: [-1, 1]}\n")
    assert make_driver(load_robot(p)).spec.state.low[0] == -1.0


def test_rig_shapes(tmp_path):
    for robots, why in (("{}", "robots: a rig needs at least one robot"),
                        ("{pm/x: {config: pointmass}}", "robots: robot name 'pm/x': use letters"),
                        ("{pm: pointmass}", "robots.pm: Input should be a valid dictionary"),
                        ("[pm]", "robots: Input should be a valid dictionary"),
                        ("{pm: {config: no_such}}", "robots.pm.config: no such robot config")):
        p = _write(tmp_path, "rig.yaml", f"name: r\nrobots: {robots}\n")
        with pytest.raises(ConfigError, match=rf"{p}: {re.escape(why)}"):
            load_rig(p)


def test_a_lockstep_rig_with_a_wall_clock_robot_is_a_config_error(tmp_path):
    p = _write(tmp_path, "rig.yaml", "name: r\npace: lockstep\nrobots: {roach: {config: velociroach, backend: emulated}}\n")
    with pytest.raises(ConfigError, match=rf"{p}: robots.roach.backend: pace 'lockstep' steps simulations"):
        load_rig(p)
    # the backend from the robot file: the rig's pace is what to change
    robot = _write(tmp_path, "roach.yaml", "robot: velociroach\nbackend: real\nparams: {port: /dev/null}\n")
    p = _write(tmp_path, "rig2.yaml", f"name: r\npace: lockstep\nrobots: {{roach: {{config: {robot}}}}}\n")
    with pytest.raises(ConfigError, match=rf"{p}: pace: .*'real' backend"):
        load_rig(p)


def test_hil_up_of_a_lockstep_rig_with_an_emulated_robot_exits_2_without_hanging(tmp_path):
    """It gave a traceback, then hung ignoring SIGTERM (the half-built driver node kept its
    Zenoh session); now the rig is refused before anything starts."""
    p = _write(tmp_path, "rig.yaml", "name: r\npace: lockstep\nrobots: {roach: {config: velociroach, backend: emulated}}\n")
    line = _one_error_line(_hil(["up", str(p), "--steps", "3"], timeout_s=120))
    assert line.startswith(f"error: {p}: robots.roach.backend: pace 'lockstep'"), line


def test_a_typo_in_a_rig_entrys_params_is_blamed_on_the_rig(tmp_path):
    from hilstack.configs.schema import rig_robot_config

    p = _write(tmp_path, "rig.yaml", "name: r\nrobots: {pm: {config: pointmass, params: {mas_kg: 1}}}\n")
    with pytest.raises(ConfigError) as e:
        make_driver(rig_robot_config(load_rig(p), "pm"))
    assert e.value.file == str(p) and e.value.problems[0][0] == "robots.pm.params.mas_kg", e.value
    # a bad value the rig sets, and a backend the robot does not have: the rig file too
    p = _write(tmp_path, "rig.yaml", "name: r\nrobots: {pm: {config: pointmass, params: {period_s: .inf}}}\n")
    with pytest.raises(ConfigError, match=rf"{p}: robots.pm.params.period_s: Input should be a finite number"):
        make_driver(rig_robot_config(load_rig(p), "pm"))
    p = _write(tmp_path, "rig.yaml", "name: r\nrobots: {pm: {config: pointmass, backend: real}}\n")
    with pytest.raises(ConfigError, match=rf"{p}: robots.pm.backend: robot 'pointmass' has no 'real' backend"):
        make_driver(rig_robot_config(load_rig(p), "pm"))
    # what the robot file itself gets wrong stays the robot file's
    robot = _write(tmp_path, "pm.yaml", "robot: pointmass\nparams: {mass_kg: -1}\n")
    p = _write(tmp_path, "rig.yaml", f"name: r\nrobots: {{pm: {{config: {robot}, params: {{period_s: 0.02}}}}}}\n")
    with pytest.raises(ConfigError, match=rf"{robot}: params.mass_kg: Input should be greater than 0"):
        make_driver(rig_robot_config(load_rig(p), "pm"))


def test_hil_up_names_the_rig_file_for_its_entrys_typo(tmp_path):
    p = _write(tmp_path, "rig.yaml", "name: r\nrobots: {pm: {config: pointmass, params: {mas_kg: 1}}}\n")
    line = _one_error_line(_hil(["up", str(p), "--steps", "1"]))
    assert line.startswith(f"error: {p}: robots.pm.params.mas_kg: unknown field"), line


def test_a_driver_node_refused_for_its_pace_leaves_nothing_running(tmp_path):
    """The hang behind item 12's lockstep rig: DriverNode refused the pace after opening its
    Zenoh session and taking SIGTERM, so the process lived on. It now refuses first."""
    code = ("from hilstack.drivers.bridge import DriverNode\n"
            "from hilstack.drivers.registry import make_driver\n"
            "DriverNode(make_driver('velociroach', backend='emulated'), 'r', 'roach', pace='lockstep')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert r.returncode == 1 and "pace 'lockstep' needs a sim backend" in r.stderr, r.stderr[-500:]


def test_the_mechanism_range_cannot_collapse(tmp_path):
    """Found by `hil bench fuzz --target robot_config`: rotate_half_range_deg 1e-300 passed
    gt=0 and made the action range [-0, 0]."""
    for field, v in (("rotate_half_range_deg", "1.0e-300"), ("rail_half_travel_m", "1.0e-9")):
        p = _write(tmp_path, "m.yaml", f"robot: reset_mechanism\nbackend: sim\nparams: {{{field}: {v}}}\n")
        with pytest.raises(ConfigError, match=rf"{p}: params.{field}: Input should be greater than or equal to"):
            make_driver(load_robot(p))
