"""The camera tracker on the bus: a driver node publishes the tracked balls and JPEG images
under hil/<rig>/camera/..., the recorder writes them (and foxglove.CompressedImage), and the
recording converts to a rerun .rrd with the images and the 3-D points."""

from __future__ import annotations

import threading

import numpy as np
from typer.testing import CliRunner

from hilstack.bus import keys
from hilstack.bus.recording import Recorder, foxglove_image_topic, read_messages, summarize
from hilstack.bus.schemas import Image, RobotState
from hilstack.configs.schema import load_rig, rig_robot_config
from hilstack.drivers.bridge import DriverNode
from hilstack.drivers.registry import make_driver


def test_camera_rig_on_the_bus_records_and_plays_back_in_rerun(tmp_path, bus):
    import rerun as rr

    from hilstack.tools.cli import app

    rig = load_rig("hand_camera_sim")
    drv = make_driver(rig_robot_config(rig, "camera"))
    mc = tmp_path / "cam.mcap"
    rec = Recorder(rig.name, mc, bus=bus)
    node = DriverNode(drv, rig.name, "camera", bus=bus, pace=rig.pace, estop_sync_s=0.1)
    t = threading.Thread(target=node.serve, kwargs={"max_steps": 8})
    t.start()
    t.join(timeout=120)
    assert not t.is_alive()
    rec.record(seconds=0.3)
    node.close()

    msgs = read_messages(mc).messages
    states = [m.msg for m in msgs if isinstance(m.msg, RobotState)]
    images = [m for m in msgs if isinstance(m.msg, Image)]
    assert states and images
    assert images[0].topic == keys.image(rig.name, "camera")
    assert images[0].msg.encoding == "jpeg" and (images[0].msg.width, images[0].msg.height) == (560, 180)
    s = states[-1].state
    assert len(s) == 8 and min(s[6:]) > 0.5  # both balls confidently tracked
    assert np.linalg.norm(np.array(s[:3]) - [0.0, -0.02, 0.34]) < 0.04  # on the palm, hand frame
    other = summarize(mc)["other_channels"]
    assert other[foxglove_image_topic(rig.name, "camera")]["schema"] == "foxglove.CompressedImage"

    rrd = tmp_path / "cam.rrd"
    r = CliRunner().invoke(app, ["viz", "--recording", str(mc), "--save", str(rrd)])
    assert r.exit_code == 0, r.output
    comps: dict[str, set[str]] = {}
    for c in rr.chunk.RrdReader(str(rrd)).stream().to_chunks():
        comps.setdefault(str(c.entity_path), set()).update(c.to_record_batch().schema.names)
    assert any("EncodedImage:blob" in n for n in comps.get("/camera/camera", set())), comps.keys()
    assert any("Points3D:positions" in n for n in comps.get("/world/camera/balls", set())), comps.keys()
