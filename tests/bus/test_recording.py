"""Record → replay round trip, third-party readers, truncated files, inspect."""

from __future__ import annotations

import threading
import time

import pytest

from bus import keys
from bus.node import Node
from bus.recording import McapLog, Recorder, read_messages, replay, summarize
from bus.schemas import Command, Image, Plan, RobotState

RIG = "rec_test"


def _sample_messages() -> list[tuple[str, object]]:
    out = []
    for i in range(50):
        out.append((keys.state(RIG, "pm"), RobotState(robot="pm", t_s=i * 0.02, state=[i * 0.1, -1.5, 0.25, 1e-9],
                                                      seq=i + 1, stamp_s=1000.0 + i * 0.02, health={"ok": True})))
        out.append((keys.cmd(RIG, "pm"), Command(robot="pm", action=[0.5, -0.5], seq=i + 1, stamp_s=1000.0 + i * 0.02)))
    out.append((keys.plan(RIG), Plan(robot="pm", actions=[[0.1, 0.2]] * 3, states=[[0.0] * 4] * 4, cost=1.5,
                                     seq=1, stamp_s=1001.0)))
    out.append((keys.image(RIG, "cam"), Image(camera="cam", t_s=1.0, width=2, height=1, data=bytes(range(6)),
                                              seq=1, stamp_s=1001.0)))
    return out


def test_mcap_log_readable_by_mcap_reader_and_back(tmp_path):
    path = tmp_path / "a.mcap"
    msgs = _sample_messages()
    with McapLog(path) as log:
        for t, m in msgs:
            log.write(t, m)
    back = read_messages(path)
    assert not back.truncated
    assert [(r.topic, r.msg) for r in back.messages] == msgs
    # third-party reader: the mcap package with its own JSON decoding
    import json

    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert {c.topic for c in summary.channels.values()} == {t for t, _ in msgs}
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
        n = 0
        for schema, channel, message in reader.iter_messages():
            obj = json.loads(message.data)
            assert obj["type"] == schema.name and channel.message_encoding == "json"
            n += 1
        assert n == len(msgs)


def test_rerun_mcap_reader_decodes_it(tmp_path):
    import rerun as rr
    path = tmp_path / "b.mcap"
    with McapLog(path) as log:
        for t, m in _sample_messages():
            log.write(t, m)
    reader = rr.chunk.McapReader(str(path))
    topics = set()
    for chunk in reader.stream().to_chunks():
        topics.add(str(chunk.entity_path))
    assert any("pm/state" in t for t in topics), topics


def test_truncated_file_keeps_everything_before_the_damage(tmp_path):
    path = tmp_path / "c.mcap"
    log = McapLog(path, chunk_size=2048)
    msgs = _sample_messages()
    for t, m in msgs:
        log.write(t, m)
    log._f.flush()  # simulate a crash: no finish(), file cut mid-chunk
    data = path.read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: int(len(data) * 0.8)])
    back = read_messages(tmp_path / "cut.mcap")
    assert back.truncated
    assert 0 < len(back.messages) < len(msgs)
    assert [(r.topic, r.msg) for r in back.messages] == msgs[: len(back.messages)]
    s = summarize(tmp_path / "cut.mcap")
    assert s["truncated"] and s["messages"] == len(back.messages)


def test_record_replay_round_trip_equality(tmp_path, bus):
    first = tmp_path / "first.mcap"
    second = tmp_path / "second.mcap"
    msgs = _sample_messages()

    rec = Recorder(RIG, first, bus, handle_signals=False)
    pub = Node("pub", RIG, bus, handle_signals=False)
    time.sleep(0.5)  # discovery
    for t, m in msgs:
        from bus.schemas import encode

        pub.session.put(t, encode(m))
        time.sleep(0.001)
    time.sleep(0.5)
    rec.close()
    pub.close()
    rec1 = read_messages(first).messages
    assert [r.msg for r in rec1] == [m for _, m in msgs]

    rec2 = Recorder(RIG, second, bus, handle_signals=False)
    th = threading.Thread(target=rec2.record, kwargs={"seconds": 3.0})
    th.start()
    time.sleep(0.5)
    n = replay(first, bus, speed=0)
    th.join()
    rec2.close()
    assert n == len(msgs)
    rec2_msgs = read_messages(second).messages
    assert [(r.topic, r.msg) for r in rec2_msgs] == [(r.topic, r.msg) for r in rec1]


def test_replay_speed_scales_timing(tmp_path, bus):
    path = tmp_path / "d.mcap"
    with McapLog(path) as log:
        for i in range(11):
            log.write(keys.cmd(RIG, "pm"), Command(robot="pm", action=[float(i)]), log_time_ns=int(i * 0.05e9))
    t = time.monotonic()
    replay(path, bus, speed=1.0)
    t1 = time.monotonic() - t
    t = time.monotonic()
    replay(path, bus, speed=5.0)
    t5 = time.monotonic() - t
    assert t1 >= 0.5 * 0.95  # 0.5 s of log time at 1x
    assert t5 < t1


def test_inspect_cli(tmp_path):
    from typer.testing import CliRunner

    from tools.cli import app

    path = tmp_path / "e.mcap"
    with McapLog(path) as log:
        for i, (t, m) in enumerate(_sample_messages()):
            log.write(t, m, log_time_ns=int(i * 1e7))
    r = CliRunner().invoke(app, ["inspect", str(path), "--json"])
    assert r.exit_code == 0, r.output
    import json

    s = json.loads(r.stdout)
    assert s["channels"][keys.state(RIG, "pm")]["count"] == 50
    assert s["channels"][keys.state(RIG, "pm")]["rate_hz"] == pytest.approx(50, rel=0.05)
    r = CliRunner().invoke(app, ["inspect", str(tmp_path / "missing.mcap")])
    assert r.exit_code == 2
