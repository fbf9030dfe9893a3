"""Recordings in third-party tools: Foxglove's schema rules, protobuf well-known schemas,
rerun's MCAP importer, and our own readers beside the extra channels."""

from __future__ import annotations

import base64
import json
import math

import msgspec
import pytest
from mcap.reader import make_reader

from hilstack.bus import keys
from hilstack.bus.recording import (
    McapLog,
    foxglove_image_topic,
    foxglove_pose_topic,
    foxglove_tf_topic,
    read_messages,
    summarize,
)
from hilstack.bus.schemas import ALL_TYPES, Command, Image, Plan, RobotState, SpecMsg, json_schema, type_name
from tests.helpers import spec_dict

RIG = "fox"
NAMES = ["x", "y", "cos_yaw", "sin_yaw", "v"]
SPEC = {**spec_dict("bot", NAMES, ["u"]),
        "state": {"names": NAMES, "units": ["m", "m", "1", "1", "m/s"], "low": [-1e9] * 5, "high": [1e9] * 5}}


# --------------------------------------------------------------------------- Foxglove's rules
class FoxgloveSchemaError(ValueError):
    pass


def foxglove_parse_json_schema(schema: dict, type_name_: str) -> dict[str, list[dict]]:
    """A Python port of Foxglove's ``parseJsonSchema`` (foxglove/studio,
    packages/mcap-support/src/parseJsonSchema.ts): the JSON-schema -> message datatypes
    step Foxglove runs on every ``jsonschema`` channel. Returns {type name: fields};
    raises where the TypeScript throws (including the TypeError of
    ``Object.entries(undefined)`` on an object without ``properties``)."""
    datatypes: dict[str, list[dict]] = {}

    def add(sch: dict, tname: str, key_path: list[str]) -> None:
        if not isinstance(sch, dict) or sch.get("type") != "object":
            got = sch.get("type") if isinstance(sch, dict) else sch
            raise FoxgloveSchemaError(f'Expected "type": "object" for schema {tname}, got {json.dumps(got)}')
        props = sch.get("properties")
        if not isinstance(props, dict):
            raise FoxgloveSchemaError(f"TypeError: Cannot convert undefined or null to object ({tname})")
        fields: list[dict] = []
        for name, fs in props.items():
            where = ".".join([*key_path, name])
            if isinstance(fs.get("oneOf"), list):
                if all(isinstance(alt.get("const"), (int, float)) for alt in fs["oneOf"]):
                    fields += [{"name": alt.get("title"), "type": "uint32", "isConstant": True} for alt in fs["oneOf"]]
                    fields.append({"name": name, "type": "uint32"})
                    continue
                raise FoxgloveSchemaError(f"Unsupported type for {where}: oneOf alternatives must have number values")
            t = fs.get("type")
            if t == "boolean":
                fields.append({"name": name, "type": "bool"})
            elif t == "string":
                enc = fs.get("contentEncoding")
                if enc is None:
                    fields.append({"name": name, "type": "string"})
                elif enc == "base64":
                    fields.append({"name": name, "type": "uint8", "isArray": True, "base64": True})
                else:
                    raise FoxgloveSchemaError(f"Unsupported contentEncoding {json.dumps(enc)} in {where}")
            elif t == "number":
                fields.append({"name": name, "type": "float64"})
            elif t == "integer":
                fields.append({"name": name, "type": "uint32"})
            elif t == "object":
                nested = f"{tname}.{name}"
                add(fs, nested, [*key_path, name])
                fields.append({"name": name, "type": nested, "isComplex": True})
            elif t == "array":
                items = fs.get("items")
                it = items.get("type") if isinstance(items, dict) else None
                if it == "boolean":
                    fields.append({"name": name, "type": "bool", "isArray": True})
                elif it == "string":
                    if items.get("contentEncoding") is not None:
                        raise FoxgloveSchemaError(f"Unsupported contentEncoding for array item {where}")
                    fields.append({"name": name, "type": "string", "isArray": True})
                elif it == "number":
                    fields.append({"name": name, "type": "float64", "isArray": True})
                elif it == "integer":
                    fields.append({"name": name, "type": "uint32", "isArray": True})
                elif it == "object":
                    nested = f"{tname}.{name}"
                    add(items, nested, [*key_path, name])
                    fields.append({"name": name, "type": nested, "isComplex": True, "isArray": True})
                else:
                    raise FoxgloveSchemaError(f"Unsupported type {json.dumps(it)} for array item {where}")
            else:
                raise FoxgloveSchemaError(f"Unsupported type {json.dumps(t)} for {where}")
        datatypes[tname] = fields

    add(schema, type_name_, [])
    return datatypes


def conforms(value: object, tname: str, datatypes: dict[str, list[dict]], where: str = "") -> None:
    """The recorded JSON value has the shape the parsed datatypes promise (fields Foxglove
    knows are of the declared kind; null stands for a non-finite float64)."""
    assert isinstance(value, dict), f"{where or tname}: expected an object, got {value!r}"
    kinds = {"bool": bool, "string": str, "float64": (int, float, type(None)), "uint32": int}
    for f in datatypes[tname]:
        if f.get("isConstant") or f["name"] not in value:
            continue
        v, here = value[f["name"]], f"{where}.{f['name']}"
        if f.get("base64"):
            assert isinstance(v, str), here
            base64.b64decode(v, validate=True)
            continue
        vals = v if f.get("isArray") else [v]
        if f.get("isArray"):
            assert isinstance(v, list), f"{here}: expected an array, got {v!r}"
        for x in vals:
            if f.get("isComplex"):
                conforms(x, f["type"], datatypes, here)
            else:
                assert isinstance(x, kinds[f["type"]]) and not (f["type"] == "uint32" and isinstance(x, bool)), \
                    f"{here}: {x!r} is not {f['type']}"
                if f["type"] == "uint32":
                    assert 0 <= x < 2**32, f"{here}: {x} outside uint32"


def test_checker_rejects_what_foxglove_rejects():
    """The port fails on the four defects of msgspec's raw schemas named in the issue."""
    raw = {t: msgspec.json.schema(t) for t in ALL_TYPES}
    with pytest.raises(FoxgloveSchemaError, match='Expected "type": "object"'):  # root is a $ref
        foxglove_parse_json_schema(raw[Command], "hil.Command/1")
    inner = {t: r["$defs"][t.__name__] for t, r in raw.items()}
    with pytest.raises(FoxgloveSchemaError, match='Unsupported type undefined|Unsupported type null'):
        foxglove_parse_json_schema(inner[Command], "c")  # tag: enum without a type
    no_tag = {k: v for k, v in inner[SpecMsg]["properties"].items() if k != "type"}
    with pytest.raises(FoxgloveSchemaError, match="Cannot convert undefined"):  # spec: object, no properties
        foxglove_parse_json_schema({**inner[SpecMsg], "properties": no_tag}, "s")
    no_tag = {k: v for k, v in inner[Plan]["properties"].items() if k != "type"}
    with pytest.raises(FoxgloveSchemaError, match="for array item actions"):  # array of arrays
        foxglove_parse_json_schema({**inner[Plan], "properties": no_tag}, "p")


@pytest.mark.parametrize("typ", ALL_TYPES, ids=lambda t: t.__name__)
def test_every_recorded_schema_passes_foxglove_rules(typ):
    dt = foxglove_parse_json_schema(json_schema(typ), type_name(typ))
    fields = {f["name"]: f for f in dt[type_name(typ)]}
    assert fields["type"]["type"] == "string" and fields["seq"]["type"] == "uint32"
    assert set(fields) == set(typ.__struct_fields__) | {"type"}


def _recording(path, n=20):
    """A rig session: spec, states moving along a quarter circle, commands, a plan, an image."""
    msgs = [(keys.spec(RIG, "bot"), SpecMsg(robot="bot", spec=SPEC, seq=1, stamp_s=1000.0))]
    for i in range(n):
        yaw = i * math.pi / 2 / (n - 1)
        st = [math.cos(yaw), math.sin(yaw), math.cos(yaw + math.pi / 2), math.sin(yaw + math.pi / 2), 0.1]
        msgs.append((keys.state(RIG, "bot"), RobotState(robot="bot", t_s=0.1 * i, state=st, action=[0.5],
                                                       seq=i + 1, stamp_s=1000.0 + 0.1 * i, health={"ok": True})))
        msgs.append((keys.cmd(RIG, "bot"), Command(robot="bot", action=[0.5], seq=i + 1, stamp_s=1000.0 + 0.1 * i)))
    msgs.append((keys.plan(RIG), Plan(robot="bot", actions=[[0.1], [0.2]], states=[[0.0] * 5] * 3, seq=1,
                                      stamp_s=1001.0)))
    msgs.append((keys.image(RIG, "cam"), Image(camera="cam", t_s=1.0, width=2, height=1, data=bytes(range(6)),
                                               seq=1, stamp_s=1001.0)))
    with McapLog(path) as log:
        for i, (t, m) in enumerate(msgs):
            log.write(t, m, log_time_ns=int(1000e9) + i * 1_000_000)
    return msgs


def test_recording_opens_under_foxglove_rules_with_robot_poses(tmp_path):
    """Every jsonschema channel parses under Foxglove's rules and each message conforms;
    the robot pose is on Foxglove's well-known PoseInFrame/FrameTransform (protobuf),
    decoded here from the schema stored in the file (mcap-protobuf-support)."""
    from mcap_protobuf.decoder import DecoderFactory

    path = tmp_path / "fox.mcap"
    msgs = _recording(path)
    seen: dict[str, int] = {}
    poses, tfs = [], []
    with open(path, "rb") as f:
        protobuf = DecoderFactory()
        for schema, channel, message in make_reader(f).iter_messages():
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            if schema.encoding == "jsonschema":
                assert channel.message_encoding == "json"
                dt = foxglove_parse_json_schema(json.loads(schema.data), schema.name)
                conforms(json.loads(message.data), schema.name, dt)
            else:
                assert (schema.encoding, channel.message_encoding) == ("protobuf", "protobuf")
                decoded = protobuf.decoder_for(channel.message_encoding, schema)(message.data)
                (poses if schema.name == "foxglove.PoseInFrame" else tfs).append(decoded)
    n_states = sum(isinstance(m, RobotState) for _, m in msgs)
    assert seen[foxglove_pose_topic(RIG, "bot")] == n_states
    assert seen[foxglove_tf_topic(RIG)] == n_states
    assert len(poses) == len(tfs) == n_states
    last = poses[-1]
    assert last.frame_id == "world"
    assert (last.pose.position.x, last.pose.position.y) == pytest.approx((0.0, 1.0), abs=1e-9)
    # the state's heading is 180 deg at the end: quaternion about z
    q = last.pose.orientation
    assert (q.x, q.y, abs(q.z), q.w) == pytest.approx((0.0, 0.0, 1.0, 0.0), abs=1e-9)
    assert (tfs[0].parent_frame_id, tfs[0].child_frame_id) == ("world", "bot")
    assert tfs[0].timestamp.seconds == 1000 and tfs[1].timestamp.nanos == pytest.approx(1e8, abs=1e3)


def test_our_readers_ignore_the_foxglove_channels(tmp_path, bus):
    from hilstack.bus.recording import replay
    from hilstack.learning.recordings import episodes_from_mcap

    path = tmp_path / "ours.mcap"
    msgs = _recording(path)
    back = read_messages(path)
    assert not back.truncated and back.undecodable == 0
    assert [(r.topic, r.msg) for r in back.messages] == msgs  # nested arrays, bytes: as written
    s = summarize(path)
    assert s["messages"] == len(msgs)
    assert s["other_channels"][foxglove_pose_topic(RIG, "bot")] == {"schema": "foxglove.PoseInFrame", "count": 20}
    eps = episodes_from_mcap(path)
    assert len(eps) == 1 and eps[0].states.shape == (20, 5)
    assert replay(path, bus, speed=0, include_commands=True).published == len(msgs)
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    r = CliRunner().invoke(app, ["inspect", str(path)])
    assert r.exit_code == 0, r.output
    assert f"{len(msgs)} messages" in r.output
    derived = [line for line in r.output.splitlines() if "(derived, not replayed)" in line]
    assert len(derived) == 4 and any("foxglove.PoseInFrame" in line and " 20 " in line for line in derived)
    assert any("hil.StateFields/bot" in line and " 20 " in line for line in derived)
    assert any("hil.Timing" in line and " 20 " in line for line in derived)


def test_state_fields_are_named_for_foxglove(tmp_path):
    """Foxglove plots ``state.v`` from the per-robot fields channel: its schema names every
    state and action channel (parsed by the port of Foxglove's rules) and the values are the state's."""
    from hilstack.bus.recording import state_fields_topic

    path = tmp_path / "fields.mcap"
    msgs = _recording(path)
    states = [m for _, m in msgs if isinstance(m, RobotState)]
    got = []
    with open(path, "rb") as f:
        for schema, _channel, message in make_reader(f).iter_messages(topics=[state_fields_topic(RIG, "bot")]):
            dt = foxglove_parse_json_schema(json.loads(schema.data), schema.name)
            got.append(json.loads(message.data))
    assert schema.name == "hil.StateFields/bot"
    assert [f["name"] for f in dt["hil.StateFields/bot.state"]] == NAMES
    assert [f["name"] for f in dt["hil.StateFields/bot.action"]] == ["u"]
    assert len(got) == len(states)
    for rec, st in zip(got, states, strict=True):
        assert rec["state"] == dict(zip(NAMES, st.state, strict=True)) and rec["action"] == {"u": 0.5}


def test_rerun_loads_the_recording(tmp_path):
    """Done-when of the issue: the recording opens in rerun (its MCAP importer)."""
    import rerun as rr

    path = tmp_path / "rr.mcap"
    _recording(path)
    paths = {str(c.entity_path) for c in rr.chunk.McapReader(str(path)).stream().to_chunks()}
    for topic in (keys.state(RIG, "bot"), keys.cmd(RIG, "bot"), keys.plan(RIG), foxglove_pose_topic(RIG, "bot")):
        assert any(topic in p for p in paths), (topic, sorted(paths))
    # and the viewer's own checker (`rerun mcap check --full`) decodes every channel
    import os
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-m", "rerun", "mcap", "check", "--full", str(path)], capture_output=True,
                       text=True, timeout=120, env={**os.environ, "RERUN_ANALYTICS": "off"})
    assert p.returncode == 0, p.stderr
    status = {line.split()[-2]: line.split()[0] for line in p.stdout.splitlines() if "/hil/" in line}
    assert len(status) == 9 and set(status.values()) == {"ok"}, p.stdout  # 9: with the state fields and timing


def test_nan_state_survives_and_a_bad_message_does_not_end_reading(tmp_path):
    """JSON has no NaN (it is recorded as null): it reads back as NaN. A message that does
    not decode is skipped and counted; the messages after it are still read."""
    path = tmp_path / "nan.mcap"
    with McapLog(path) as log:
        log.write(keys.state(RIG, "bot"), RobotState(robot="bot", t_s=0.0, state=[math.nan, 1.0], seq=1))
        cid = log._channel(keys.cmd(RIG, "bot"), Command)
        log._w.add_message(cid, log_time=1, data=b'{"type":"hil.Command/1","robot":3}', publish_time=1)
        log.write(keys.cmd(RIG, "bot"), Command(robot="bot", action=[1.0], seq=2))
    back = read_messages(path)
    assert [r.msg.seq for r in back.messages] == [1, 2]
    assert math.isnan(back.messages[0].msg.state[0]) and back.messages[0].msg.state[1] == 1.0
    assert back.undecodable == 1 and "hil/fox/bot/cmd" in back.undecodable_error
    assert not back.truncated


# --------------------------------------------------------------------------- MAVLink .tlog
def test_drive_tlog_decodes_with_the_documented_dump_command(tmp_path):
    """`hil drive --tlog` on the emulated VelociRoACH (real driver over a pty) writes a
    .tlog; `python -m hilstack.drivers.velociroach.mavlink dump` (pymavlink's mavlogdump with our
    dialect) decodes every command and telemetry frame in it."""
    import subprocess
    import sys

    from typer.testing import CliRunner

    from hilstack.tools.cli import app
    from tests.helpers import ROOT

    tlog = tmp_path / "roach.tlog"
    r = CliRunner().invoke(app, ["drive", "velociroach", "--backend", "emulated", "--action", "0.5,0.5",
                                 "--seconds", "1", "--tlog", str(tlog), "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads(r.stdout)
    assert res["tlog"] == str(tlog)

    def dump(*args: str) -> list[str]:
        p = subprocess.run([sys.executable, "-m", "hilstack.drivers.velociroach.mavlink", "dump", *args, str(tlog)],
                           cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert p.returncode == 0, p.stderr
        return p.stdout.splitlines()

    cmds = [line.split(",") for line in dump("--format", "csv", "--types", "ROACH_LEG_VELOCITY_CMD")[1:]]
    seqs = [int(c[3]) for c in cmds]
    left_right = [(float(c[4]), float(c[5])) for c in cmds]
    assert seqs == sorted(set(seqs)) and len(seqs) >= res["steps"]
    assert left_right.count(tuple(res["action"])) >= res["steps"]  # 0.5 of ±15 rev/s = 7.5
    assert left_right[-1] == (0.0, 0.0)  # the stop at the end
    telemetry = dump("--types", "ROACH_TELEMETRY")
    assert telemetry and all("ROACH_TELEMETRY {" in line for line in telemetry)
    # every record of the file decodes: walk the .tlog format (>Q usec + MAVLink v2 frame:
    # 10 header bytes + payload + 2 CRC bytes, + 13 signature bytes when flagged)
    data, off, n_records = tlog.read_bytes(), 0, 0
    while off < len(data):
        assert data[off + 8] == 0xFD, f"record {n_records} at byte {off} is not a MAVLink v2 frame"
        off += 8 + 12 + data[off + 9] + (13 if data[off + 10] & 1 else 0)
        n_records += 1
    assert off == len(data)
    everything = dump()
    assert len(everything) == n_records
    assert not [line for line in everything if "BAD_DATA" in line or "UNKNOWN" in line]


def test_tlog_errors_are_one_line(tmp_path):
    import subprocess
    import sys

    from typer.testing import CliRunner

    from hilstack.tools.cli import app
    from tests.helpers import ROOT

    r = CliRunner().invoke(app, ["drive", "velociroach", "--backend", "sim", "--action", "0.5,0.5",
                                 "--seconds", "0.2", "--tlog", str(tmp_path / "x.tlog")])
    assert r.exit_code == 2 and "the sim backend has no radio link" in r.output
    assert not (tmp_path / "x.tlog").exists()
    p = subprocess.run([sys.executable, "-m", "hilstack.drivers.velociroach.mavlink", "dump", str(tmp_path / "none.tlog")],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and p.stderr.strip() == f"error: no such log file: {tmp_path / 'none.tlog'}"


# --------------------------------------------------------------------------- live Foxglove
def test_live_foxglove_websocket_serves_the_rig(bus):
    """`hil foxglove`'s node: a WebSocket client speaking Foxglove's protocol sees our
    channels advertised with schemas that pass Foxglove's rules, and receives the rig's
    states (JSON), the robot's PoseInFrame and a camera's CompressedImage (protobuf,
    decoded from the advertised schema)."""
    import struct

    import cv2
    import numpy as np
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory
    from websockets.sync.client import connect

    from hilstack.bus.node import Node
    from hilstack.bus.schemas import encode
    from hilstack.tools.foxglove_live import FoxgloveLive
    from tests.helpers import wait_for

    live = FoxgloveLive(RIG, bus, port=0, handle_signals=False)
    pub = Node("pub", RIG, bus, handle_signals=False)
    state_topic, pose_topic = keys.state(RIG, "bot"), foxglove_pose_topic(RIG, "bot")
    image_topic = foxglove_image_topic(RIG, "cam")
    jpeg = cv2.imencode(".jpg", np.full((12, 16, 3), 200, np.uint8))[1].tobytes()
    try:
        with connect(live.url, subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
            channels: dict[str, dict] = {}
            subscribed: dict[int, str] = {}
            got: dict[str, list[bytes]] = {}
            i = 0

            def step() -> bool:
                nonlocal i
                i += 1
                if i == 1 or i % 20 == 0:
                    pub.session.put(keys.spec(RIG, "bot"), encode(SpecMsg(robot="bot", spec=SPEC, seq=i)))
                st = RobotState(robot="bot", t_s=0.01 * i, state=[1.0, 2.0, 0.0, 1.0, 0.1], seq=i, stamp_s=1000.0 + i)
                pub.session.put(state_topic, encode(st))
                pub.session.put(keys.image(RIG, "cam"), encode(Image(camera="cam", t_s=0.01 * i, width=16, height=12,
                                                                     encoding="jpeg", data=jpeg, seq=i)))
                live.pump()
                try:
                    while True:
                        frame = ws.recv(timeout=0.02)
                        if isinstance(frame, str):
                            op = json.loads(frame)
                            if op["op"] == "advertise":
                                for ch in op["channels"]:
                                    channels[ch["topic"]] = ch
                                    if ch["topic"] in (state_topic, pose_topic, image_topic):
                                        subscribed[ch["id"]] = ch["topic"]
                                        ws.send(json.dumps({"op": "subscribe",
                                                            "subscriptions": [{"id": ch["id"], "channelId": ch["id"]}]}))
                        elif frame[0] == 0x01:  # message data: sub id u32, log time u64, payload
                            (sub_id,) = struct.unpack_from("<I", frame, 1)
                            got.setdefault(subscribed[sub_id], []).append(bytes(frame[13:]))
                except TimeoutError:
                    pass
                return state_topic in got and pose_topic in got and image_topic in got

            wait_for(step, timeout_s=20.0, what="a state, a pose and an image over the Foxglove WebSocket")
    finally:
        pub.close()
        live.close()
    ch = channels[state_topic]
    assert (ch["encoding"], ch["schemaEncoding"], ch["schemaName"]) == ("json", "jsonschema", "hil.RobotState/1")
    foxglove_parse_json_schema(json.loads(ch["schema"]), ch["schemaName"])
    state = json.loads(got[state_topic][-1])
    assert state["robot"] == "bot" and state["state"] == [1.0, 2.0, 0.0, 1.0, 0.1]
    pch = channels[pose_topic]
    assert (pch["encoding"], pch["schemaName"]) == ("protobuf", "foxglove.PoseInFrame")
    schema = Schema(id=1, name=pch["schemaName"], encoding="protobuf", data=base64.b64decode(pch["schema"]))
    pose = DecoderFactory().decoder_for("protobuf", schema)(got[pose_topic][-1])
    assert (pose.frame_id, pose.pose.position.x, pose.pose.position.y) == ("world", 1.0, 2.0)
    assert pose.pose.orientation.z == pytest.approx(math.sin(math.pi / 4))  # yaw 90 deg
    assert foxglove_tf_topic(RIG) in channels
    ich = channels[image_topic]
    assert (ich["encoding"], ich["schemaName"]) == ("protobuf", "foxglove.CompressedImage")
    schema = Schema(id=2, name=ich["schemaName"], encoding="protobuf", data=base64.b64decode(ich["schema"]))
    img = DecoderFactory().decoder_for("protobuf", schema)(got[image_topic][-1])
    assert (img.format, img.frame_id, bytes(img.data)) == ("jpeg", "cam", jpeg)


def test_live_foxglove_busy_port_is_a_one_line_error(bus):
    import socket

    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = CliRunner().invoke(app, ["foxglove", "--rig", RIG, "--port", str(port), "--seconds", "0.1",
                                     "--endpoint", bus.endpoint])
    assert r.exit_code == 2 and f"cannot serve Foxglove on 127.0.0.1:{port}" in r.output
    assert "Traceback" not in r.output


def test_recordings_made_before_the_row_format_still_read(tmp_path):
    """Files written before this change hold Plan.actions as plain nested lists."""
    path = tmp_path / "old.mcap"
    plan = Plan(robot="bot", actions=[[0.1, 0.2], [0.3, 0.4]], states=[[1.0], [2.0], [3.0]], seq=7)
    with McapLog(path) as log:
        cid = log._channel(keys.plan(RIG), Plan)
        log._w.add_message(cid, log_time=1, data=msgspec.json.encode(plan), publish_time=1)
    back = read_messages(path)
    assert [r.msg for r in back.messages] == [plan] and back.undecodable == 0


def test_a_jpeg_frame_is_stored_once_and_reads_back_whole(tmp_path):
    """Each JPEG/PNG frame's bytes are in the MCAP once (the CompressedImage Foxglove and rerun
    show), not also as base64 in the hil.Image JSON; our reader gives the image back whole."""
    import numpy as np
    from mcap.reader import make_reader

    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, 3000, dtype=np.uint8).tobytes() for _ in range(5)]  # incompressible, as JPEG
    path = tmp_path / "cam.mcap"
    with McapLog(path) as log:
        for i, data in enumerate(frames):
            log.write(keys.image(RIG, "cam"), Image(camera="cam", t_s=0.1 * i, width=40, height=25, encoding="jpeg",
                                                    data=data, seq=i), log_time_ns=10**9 + i)
        log.write(keys.image(RIG, "raw"), Image(camera="raw", t_s=0.0, width=2, height=1, data=bytes(range(6))))
    with open(path, "rb") as f:
        payloads = [(ch.topic, m.data) for _, ch, m in make_reader(f).iter_messages()]
    for data in frames:
        b64 = base64.b64encode(data)
        assert sum(p.count(data) for _, p in payloads) == 1
        assert sum(p.count(b64) for _, p in payloads) == 0
    assert sum(t == foxglove_image_topic(RIG, "cam") for t, _ in payloads) == 5
    # the file is about the frames' size once (it was about twice with the base64 copy)
    assert path.stat().st_size < 1.3 * sum(map(len, frames))
    got = [m.msg for m in read_messages(path).messages if isinstance(m.msg, Image)]
    assert [g.data for g in got] == [*frames, bytes(range(6))]  # the raw frame is kept as it was
    assert [(g.seq, g.encoding, g.width) for g in got[:5]] == [(i, "jpeg", 40) for i in range(5)]


def test_timing_counters_are_recorded_per_robot(tmp_path):
    """hil.Timing beside each robot's states: loop rate, the longest period, states missing from
    the recording (obs_seq gaps) and the driver node's deadline counters, plottable in Foxglove."""
    from mcap.reader import make_reader

    from hilstack.bus.recording import TimingCounters, timing_topic

    path = tmp_path / "t.mcap"
    seqs = [*range(0, 10), *range(12, 30)]  # states 10 and 11 never reached the recorder
    with McapLog(path) as log:
        log.write(keys.state(RIG, "nospec"), RobotState(robot="nospec", t_s=0.0, state=[0.0]), 0)  # no spec: none
        log.write(keys.spec(RIG, "bot"), SpecMsg(robot="bot", spec=SPEC), 0)
        for i, seq in enumerate(seqs):
            stamp = 100.0 + 0.1 * seq + (0.25 if seq >= 25 else 0.0)  # 10 Hz, one 350 ms period at 25
            if seq >= 20:  # the MPC starts at state 20; its plan for every 3rd state misses its period
                log.write(keys.plan(RIG), Plan(robot="bot", actions=[[0.0]], late=seq % 3 == 0,
                                               late_count=(seq - 18) // 3, samples=500 if seq < 26 else 180), 1 + i)
            log.write(keys.state(RIG, "bot"), RobotState(robot="bot", t_s=0.1 * seq, state=[0.0] * 5, obs_seq=seq,
                                                         stamp_s=stamp, health={"cycle_late": i // 10}), 1 + i)
    with open(path, "rb") as f:
        reader = make_reader(f)
        got = [(sch.name, json.loads(m.data)) for sch, _, m in reader.iter_messages(topics=[timing_topic(RIG, "bot")])]
    assert len(got) == len(seqs) and {n for n, _ in got} == {"hil.Timing"}
    assert timing_topic(RIG, "nospec") not in {c.topic for c in reader.get_summary().channels.values()}
    t = [g for _, g in got]
    assert t[0]["rate_hz"] is None and t[0]["dropped_states"] == 0
    assert t[9]["rate_hz"] == pytest.approx(10.0) and t[9]["dropped_states"] == 0
    assert t[10]["dropped_states"] == 2 and t[-1]["dropped_states"] == 2
    assert t[10]["period_max_ms"] == pytest.approx(300.0)  # the gap of the two lost states
    assert t[-1]["period_max_ms"] == pytest.approx(350.0) and t[-1]["cycle_late"] == 2
    assert "cycle_missed" not in t[-1]  # the driver did not say: not made up
    # the controller's late plans from its first plan on, as its latest plan counted them
    assert "late_plans" not in t[19 - 2] and [g["late_plans"] for g in t[20 - 2:]] == [(s - 18) // 3 for s in seqs[18:]]
    assert t[-1]["late_plans"] == 3
    # the planner's sample count of the latest plan (refitted to the load on the wall clock)
    assert "plan_samples" not in t[19 - 2] and t[20 - 2]["plan_samples"] == 500 and t[-1]["plan_samples"] == 180
    assert foxglove_parse_json_schema(TimingCounters.SCHEMA, "hil.Timing")
