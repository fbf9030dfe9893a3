"""A device port that does not exist: one exit code on every robot (2, a config problem:
drivers/base.py require_device), and `hil up --port/--channel`, which set it for a run
through the same schema as `--set` (issue 27, item 6)."""

import pytest
from typer.testing import CliRunner

from hilstack.configs.schema import ConfigError
from hilstack.drivers.registry import make_driver
from hilstack.tools.cli import app
from tests.helpers import free_port
from tests.test_cli import access_section

MISSING = "/nonexistent/ttyUSB9"


@pytest.mark.parametrize("robot", ["velociroach", "widowx", "reset_mechanism", "pan_unit"])
def test_a_missing_serial_port_is_exit_2_on_every_robot(robot):
    """Before: the XBee robot 2 (config), the Dynamixel ones 1 (a link error from pyserial)."""
    r = CliRunner().invoke(app, ["drive", robot, "--backend", "real", "--port", MISSING, "--seconds", "0.1"])
    assert r.exit_code == 2, r.output
    assert r.output.startswith("error: ") and f"params.port: {MISSING} does not exist" in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1


def test_a_missing_slcan_adapter_and_camera_device_are_config_errors():
    hand = make_driver("shadow_hand", backend="real", transport="slcan", channel="/nonexistent/ttyACM9")
    with pytest.raises(ConfigError, match=r"params.channel: /nonexistent/ttyACM9 does not exist"):
        hand.configure()
    cam = make_driver("camera", backend="real", left_device="/nonexistent/video9", right_device=1)
    with pytest.raises(ConfigError, match=r"params.left_device: /nonexistent/video9 does not exist"):
        cam.configure()


def test_up_port_reaches_the_robot_and_is_blamed_on_the_rig(tmp_path):
    """`hil up RIG --port P` sets the rig's real robot's params.port: the missing P (not the rig
    file's /dev/ttyUSB0) is what the driver finds, named in the rig file, exit 2."""
    r = CliRunner().invoke(app, ["credentials", "roach_real"])
    assert r.exit_code == 0, r.output

    ep = f"tcp/127.0.0.1:{free_port()}"
    r = CliRunner().invoke(app, ["up", "roach_real", "--port", MISSING, "--endpoint", ep])
    assert r.exit_code == 2, r.output
    err = r.output.strip().splitlines()[-1]
    assert f"roach_real.yaml with --set roach.params.port=\"{MISSING}\": robots.roach.params.port: {MISSING} " \
           "does not exist" in err, r.output
    for args, says in ((["roach_sim", "--port", "/dev/ttyUSB1"], "rig roach_sim has no real robot with a port "
                                                                 "(roach: sim)"),
                       (["roach_real", "--channel", "can1"], "rig roach_real has no real robot with a channel"),
                       # a --set cannot switch a safety limit off: the robot's schema bounds it
                       (["roach_real", "--set", "roach.params.firmware_watchdog_s=.inf"],
                        "robots.roach.params.firmware_watchdog_s: Input should be a finite number"),
                       (["roach_real", "--set", "roach.params.max_leg_accel_rps2=1e9"],
                        "robots.roach.params.max_leg_accel_rps2: Input should be less than or equal to 120")):
        r = CliRunner().invoke(app, ["up", *args, "--endpoint", ep])
        assert r.exit_code == 2 and says in r.output, (args, r.output)
        assert len([ln for ln in r.output.splitlines() if ln.startswith("error")]) == 1


def test_up_port_of_robots_on_one_adapter_and_on_two(tmp_path):
    """The WidowX and its mechanism on one U2D2 both get --port (one process, one config error,
    exit 2); on two adapters (the rig file gives two ports) --port must be told which robot."""
    def rig(arm_port, mech_port):
        f = tmp_path / "arm_real.yaml"
        f.write_text(f"name: arm_real\nrobots:\n  arm:\n    config: widowx\n    backend: real\n"
                     f"    params: {{port: {arm_port}}}\n  mechanism:\n    config: reset_mechanism\n"
                     f"    backend: real\n    params: {{port: {mech_port}}}\n" + access_section(tmp_path))
        return str(f)

    ep = f"tcp/127.0.0.1:{free_port()}"     # its own bus port: a default one may be taken by another run
    r = CliRunner().invoke(app, ["up", rig("/dev/ttyUSB0", "/dev/ttyUSB0"), "--port", MISSING, "--endpoint", ep])
    assert r.exit_code == 2, r.output
    # the two robots open their shared adapter side by side: whichever finds it missing first is named
    # (the other's failure is then the rig's shutdown)
    assert any(f"{n}: {tmp_path / 'arm_real.yaml'} with --set arm.params.port=\"{MISSING}\" "
               f"mechanism.params.port=\"{MISSING}\": robots.{n}.params.port: {MISSING} does not exist" in r.output
               for n in ("arm", "mechanism")), r.output
    r = CliRunner().invoke(app, ["up", rig("/dev/ttyUSB0", "/dev/ttyUSB1"), "--port", MISSING, "--endpoint", ep])
    assert r.exit_code == 2 and "robots arm, mechanism are on different devices: pick one with --robot" in r.output
