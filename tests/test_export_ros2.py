"""`hil export ros2`: a recording as a ROS 2 bag, read back with rosbags' reader (tools/export.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from typer.testing import CliRunner

from hilstack.bus.recording import McapLog
from hilstack.bus.schemas import Command, EStop, Image, RobotState, SpecMsg
from hilstack.tools.cli import app

NAMES = ["x", "y", "z", "vx", "vy", "vz", "cos_roll", "sin_roll", "cos_pitch", "sin_pitch", "cos_yaw", "sin_yaw",
         "wx", "wy", "wz", "cos_crank_l", "sin_crank_l", "crank_vel_l", "vbat"]
UNITS = ["m", "m", "m", "m/s", "m/s", "m/s", "1", "1", "1", "1", "1", "1", "rad/s", "rad/s", "rad/s", "1", "1",
         "rev/s", "V"]
SPEC = {"name": "velociroach", "period_s": 0.1,
        "state": {"names": NAMES, "units": UNITS},
        "action": {"names": ["leg_vel_l", "leg_vel_r"], "units": ["rev/s", "rev/s"]}}
JPEG = b"\xff\xd8\xff\xe0fake-jpeg-bytes\xff\xd9"


def _state(k: int) -> list[float]:
    yaw, crank = math.pi / 2, 0.3 * k
    return [0.1 * k, 0.2, 0.03, 1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, math.cos(yaw), math.sin(yaw), 0.0, 0.0, 0.5,
            math.cos(crank), math.sin(crank), 2.0, 4.1]


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    path = tmp_path / "rec.mcap"
    t0 = 1_700_000_000.0
    with McapLog(path) as log:
        log.write("hil/r/roach/state", RobotState(robot="roach", t_s=0.0, state=_state(0)), int(t0 * 1e9))  # no spec yet
        log.write("hil/r/roach/spec", SpecMsg(robot="roach", spec=SPEC), int(t0 * 1e9))
        for k in range(5):
            ns = int((t0 + 0.1 * (k + 1)) * 1e9)
            log.write("hil/r/roach/state", RobotState(robot="roach", t_s=0.1 * k, state=_state(k), stamp_s=ns / 1e9,
                                                      episode=1, seq=k), ns)
            log.write("hil/r/roach/cmd", Command(robot="roach", action=[0.5, -0.5], stamp_s=ns / 1e9, seq=k), ns)
        log.write("hil/r/left/image", Image(camera="left", t_s=0.5, width=4, height=2, encoding="jpeg", data=JPEG),
                  int((t0 + 1) * 1e9))
        log.write("hil/r/estop", EStop(engaged=True, reason="test"), int((t0 + 1.1) * 1e9))
    return path


def _read(bag: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        for c, t, raw in r.messages():
            out.setdefault(c.topic, []).append((t, r.deserialize(raw, c.msgtype)))
    out["_types"] = types  # type: ignore[assignment]
    return out


def test_roach_recording_reads_back_with_standard_types(recording, tmp_path):
    bag = tmp_path / "bag"
    r = CliRunner().invoke(app, ["export", "ros2", str(recording), "--out", str(bag)])
    assert r.exit_code == 0, r.output
    assert "1 skipped" in r.output  # the state before the spec: no names to export it with
    got = _read(bag)
    types = got["_types"]
    assert types["/r/roach/pose"] == "geometry_msgs/msg/PoseStamped"
    assert types["/r/roach/twist"] == "geometry_msgs/msg/TwistStamped"
    assert types["/r/roach/joint_states"] == "sensor_msgs/msg/JointState"
    assert types["/r/left/image/compressed"] == "sensor_msgs/msg/CompressedImage"
    assert types["/r/roach/state"] == "hilstack_msgs/msg/RobotState"
    assert types["/r/roach/cmd"] == "hilstack_msgs/msg/Command"
    assert types["/r/estop"] == "hilstack_msgs/msg/Record"
    assert len(got["/r/roach/pose"]) == 5 and len(got["/r/roach/cmd"]) == 5

    t, pose = got["/r/roach/pose"][3]
    assert pose.header.frame_id == "world" and t == int((1_700_000_000.0 + 0.4) * 1e9)
    assert pose.pose.position.x == pytest.approx(0.3) and pose.pose.position.z == pytest.approx(0.03)
    q = pose.pose.orientation  # yaw 90 deg about z
    assert (q.x, q.y) == pytest.approx((0.0, 0.0)) and (q.z, q.w) == pytest.approx((math.sqrt(0.5), math.sqrt(0.5)))
    tw = got["/r/roach/twist"][0][1].twist  # world vx = 1 at yaw 90 deg: the body moves along its -y
    assert (tw.linear.x, tw.linear.y, tw.angular.z) == pytest.approx((0.0, -1.0, 0.5), abs=1e-12)
    js = got["/r/roach/joint_states"][3][1]
    assert list(js.name) == ["crank_l"]
    assert js.position[0] == pytest.approx(0.9) and js.velocity[0] == pytest.approx(2.0 * 2 * math.pi)
    st = got["/r/roach/state"][2][1]
    assert list(st.names) == NAMES and np.allclose(st.state, _state(2)) and st.episode == 1
    cmd = got["/r/roach/cmd"][0][1]
    assert list(cmd.names) == ["leg_vel_l", "leg_vel_r"] and list(cmd.action) == [0.5, -0.5]
    img = got["/r/left/image/compressed"][0][1]
    assert img.format == "jpeg" and bytes(img.data) == JPEG
    assert json.loads(got["/r/estop"][0][1].json)["reason"] == "test"


def test_export_never_overwrites_without_force(recording, tmp_path):
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "keep").write_text("x")
    r = CliRunner().invoke(app, ["export", "ros2", str(recording), "--out", str(bag)])
    assert r.exit_code == 2 and "--force" in r.output and (bag / "keep").exists()
    r = CliRunner().invoke(app, ["export", "ros2", str(recording), "--out", str(bag), "--force"])
    assert r.exit_code == 0 and not (bag / "keep").exists()


def test_arm_joints_pair_positions_with_velocities():
    from hilstack.drivers.widowx.config import WidowXParams, widowx_spec
    from hilstack.tools.export import _layout

    st = widowx_spec(WidowXParams()).to_dict()["state"]
    lay = _layout(st["names"], st["units"])
    assert lay["pose"] is None and lay["twist"] is None
    joints = {j: (st["names"][src[1]], st["names"][vel[0]]) for j, src, vel in lay["joints"]}
    assert joints["waist"] == ("waist_pos", "waist_vel") and len(joints) == 6


def test_rerun_converts_the_exported_joint_states_to_plottable_scalars(recording, tmp_path):
    """Issue 27: rerun's own conversion (`rerun mcap convert`, its ROS 2 decoders) of the exported
    bag gives the roach's joints as named Scalars, their values those recorded."""
    import os
    import subprocess
    import sys

    import rerun as rr

    bag = tmp_path / "bag"
    assert CliRunner().invoke(app, ["export", "ros2", str(recording), "--out", str(bag)]).exit_code == 0
    (mcap,) = bag.glob("*.mcap")
    rrd = tmp_path / "bag.rrd"
    p = subprocess.run([sys.executable, "-m", "rerun", "mcap", "convert", "-d", "ros2msg", "-d", "ros2_reflection",
                        "-o", str(rrd), str(mcap)], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "RERUN_ANALYTICS": "off"})
    assert p.returncode == 0, p.stderr
    cols: dict[str, list] = {}
    for c in rr.chunk.RrdReader(str(rrd)).stream().to_chunks():
        if "joint_states" in str(c.entity_path):
            rb = c.to_record_batch()
            for f in rb.schema:
                if "Scalars" in f.name:
                    cols.setdefault(f"{c.entity_path}:{f.name}", []).extend(rb.column(f.name).to_pylist())
    pos = [v for k, v in cols.items() if k.split(":")[0].endswith("joint_states/position")]
    assert len(pos) == 1, sorted(cols)
    want = _read(bag)["/r/roach/joint_states"]
    assert len(pos[0]) == len(want) == 5
    assert [x for row in pos[0] for x in row] == pytest.approx([x for _, m in want for x in m.position])
    assert len({x for row in pos[0] for x in row}) == 5  # the crank turned: not one value repeated
