"""Record → replay round trip, third-party readers, truncated files, inspect."""

from __future__ import annotations

import threading
import time

import pytest

from hilstack.bus import keys
from hilstack.bus.node import Node
from hilstack.bus.recording import McapLog, Recorder, ReplayRefused, read_messages, replay, summarize
from hilstack.bus.schemas import AnyMsg, Command, EStop, Image, Plan, ResetEvent, RobotState, decode

RIG = "rec_test"


def rig_file(tmp_path, name: str = RIG):
    """A rig config without robots, so that `hil record --rig FILE` records hil/<name>/**
    (`hil record` takes a rig config: a mistyped name is an error)."""
    p = tmp_path / f"{name}.yaml"
    p.write_text(f"name: {name}\nrobots:\n  pm:\n    config: pointmass\n    backend: sim\n")
    return p


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
        from hilstack.bus.schemas import encode

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
    n = replay(first, bus, speed=0, include_commands=True).published
    th.join()
    rec2.close()
    assert n == len(msgs)
    rec2_msgs = read_messages(second).messages
    assert [(r.topic, r.msg) for r in rec2_msgs] == [(r.topic, r.msg) for r in rec1]


class _FakeClock:
    """Stands in for the ``time`` module inside hilstack.bus.recording: ``sleep`` advances the
    clock instead of waiting, so the replay schedule is checked without wall-clock timing."""

    def __init__(self):
        self.now_s = 100.0
        self.sleeps: list[float] = []

    def monotonic(self) -> float:
        return self.now_s

    def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.now_s += s

    def __getattr__(self, name):
        return getattr(time, name)


@pytest.mark.parametrize("speed", [1.0, 5.0])
def test_replay_speed_scales_timing(tmp_path, bus, monkeypatch, speed):
    import hilstack.bus.recording as recording

    path = tmp_path / "d.mcap"
    with McapLog(path) as log:
        for i in range(11):
            log.write(keys.state(RIG, "pm"), RobotState(robot="pm", t_s=i * 0.05, state=[float(i)]),
                      log_time_ns=int(i * 0.05e9))
    clock = _FakeClock()
    monkeypatch.setattr(recording, "time", clock)
    assert replay(path, bus, speed=speed, live_check_s=0.0).published == 11
    # one wait per message after the first, each 50 ms of log time / speed
    assert clock.sleeps == pytest.approx([0.05 / speed] * 10)
    assert clock.now_s - 100.0 == pytest.approx(0.5 / speed)


def test_inspect_cli(tmp_path):
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

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


def test_write_after_close_is_refused_and_file_unchanged(tmp_path):
    from hilstack.bus.recording import RecordingClosed

    path = tmp_path / "closed.mcap"
    log = McapLog(path)
    log.write(keys.cmd(RIG, "pm"), Command(robot="pm", action=[1.0], seq=1))
    log.close()
    size = path.stat().st_size
    with pytest.raises(RecordingClosed, match=r"closed\.mcap is closed: hil\.Command/1 on hil/rec_test/pm/cmd"):
        log.write(keys.cmd(RIG, "pm"), Command(robot="pm", action=[2.0], seq=2))
    assert log.count == 1 and path.stat().st_size == size
    assert [r.msg.seq for r in read_messages(path).messages] == [1]


def test_recorder_close_after_record_writes_nothing_more(tmp_path, bus):
    """`hil record` calls record() (which finishes the file) and then close(): messages
    arriving in between must not be 'written' into the finished file."""
    from hilstack.bus.recording import RecordingClosed
    from hilstack.bus.schemas import encode

    path = tmp_path / "rec.mcap"
    rec = Recorder(RIG, path, bus, handle_signals=False)
    pub = Node("pub", RIG, bus, handle_signals=False)
    try:
        time.sleep(0.5)  # discovery
        pub.session.put(keys.cmd(RIG, "pm"), encode(Command(robot="pm", action=[1.0], seq=1)))
        rec.record(seconds=0.3)
        n_recorded = rec.log.count
        assert n_recorded == 1
        pub.session.put(keys.cmd(RIG, "pm"), encode(Command(robot="pm", action=[2.0], seq=2)))
        time.sleep(0.2)  # the late message reaches the recorder's queue
        rec.close()
        assert rec.log.count == n_recorded
        with pytest.raises(RecordingClosed, match="is closed"):
            rec.pump()
    finally:
        rec.close()
        pub.close()
    back = read_messages(path)
    assert not back.truncated and [r.msg.seq for r in back.messages] == [1]


def test_quiet_log_reaches_disk_within_flush_period(tmp_path):
    """A few small messages (far below a chunk) are on disk once the flush period passed,
    even with no further writes, when the owner polls flush_if_due()."""
    path = tmp_path / "quiet.mcap"
    log = McapLog(path, flush_period_s=0.05)
    try:
        for i in range(3):
            log.write(keys.cmd(RIG, "pm"), Command(robot="pm", action=[float(i)], seq=i + 1))
        time.sleep(0.06)
        assert log.flush_if_due()
        assert not log.flush_if_due()  # nothing pending: no empty flush
        back = read_messages(path)  # the file is unfinished: a crash now keeps all three
        assert [r.msg.seq for r in back.messages] == [1, 2, 3]
    finally:
        log.close()


def test_sigkill_loses_at_most_one_second(tmp_path, bus, spawn):
    """`hil record` in a child process, fed at a known rate, killed with SIGKILL: the file
    holds a gap-free prefix of what was sent, missing at most one second's worth of it."""
    import signal

    from hilstack.bus.schemas import Ping, encode
    from tests.helpers import wait_for

    rate_hz = 100
    path = tmp_path / "killed.mcap"
    child = spawn("record", "--rig", str(rig_file(tmp_path)), "--out", str(path), "--endpoint", bus.endpoint)
    pub = Node("pub", RIG, bus, handle_signals=False)
    try:
        # warm up until the recorder is subscribed *and* its data is on disk: proves the
        # time-based flush (64 KiB chunks would keep these few pings in memory)
        n_ping = 0

        def recorded_a_ping() -> bool:
            nonlocal n_ping
            n_ping += 1
            pub.session.put(keys.root(RIG) + "/ping", encode(Ping(seq=n_ping)))
            return path.exists() and any(isinstance(r.msg, Ping) for r in read_messages(path).messages)

        wait_for(recorded_a_ping, timeout_s=20.0, what="the first recorded message on disk")
        n_sent = 300  # 3 s of data
        for i in range(n_sent):
            pub.session.put(keys.cmd(RIG, "pm"), encode(Command(robot="pm", action=[float(i)], seq=i + 1)))
            time.sleep(1.0 / rate_hz)
        child.p.send_signal(signal.SIGKILL)
        child.p.wait(10)
    finally:
        pub.close()
    back = read_messages(path)
    assert back.truncated  # killed: no footer
    seqs = [r.msg.seq for r in back.messages if isinstance(r.msg, Command)]
    assert seqs == list(range(1, len(seqs) + 1))  # in order, nothing lost in the middle
    assert n_sent - len(seqs) <= rate_hz * 1.0, f"lost {n_sent - len(seqs)} of {n_sent} messages at {rate_hz} Hz"


def test_close_from_another_thread_ends_record_cleanly(tmp_path, bus):
    from hilstack.bus.schemas import encode

    path = tmp_path / "threaded.mcap"
    rec = Recorder(RIG, path, bus, handle_signals=False)
    pub = Node("pub", RIG, bus, handle_signals=False)
    errors: list[BaseException] = []
    finish = rec.log.close

    def slow_finish() -> None:  # the recording thread polls while close() is still busy
        finish()
        time.sleep(0.2)

    rec.log.close = slow_finish

    def run() -> None:
        try:
            rec.record()
        except BaseException as e:  # noqa: BLE001 - the test reports it
            errors.append(e)

    th = threading.Thread(target=run)
    th.start()
    try:
        time.sleep(0.5)  # discovery
        for i in range(200):
            pub.session.put(keys.cmd(RIG, "pm"), encode(Command(robot="pm", action=[float(i)], seq=i + 1)))
        time.sleep(0.3)
        rec.close()
        th.join(10)
    finally:
        pub.close()
    assert not th.is_alive() and errors == []
    back = read_messages(path)
    assert not back.truncated and [r.msg.seq for r in back.messages] == list(range(1, 201))


def test_repair_turns_a_crashed_file_into_a_finished_one(tmp_path):
    """rerun and the indexed mcap reader refuse a file without its end; `hil repair` copies
    everything up to the damage into a finished file."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    crashed = tmp_path / "crashed.mcap"
    log = McapLog(crashed)
    msgs = _sample_messages()
    for t, m in msgs:
        log.write(t, m)
    log.flush()  # on disk, like a SIGKILL right after a periodic flush: no summary, no end magic
    with open(crashed, "rb") as f, pytest.raises(McapError):
        make_reader(f).get_summary()
    fixed = tmp_path / "fixed.mcap"
    r = CliRunner().invoke(app, ["repair", str(crashed), "--out", str(fixed)])
    assert r.exit_code == 0, r.output
    assert f"wrote {len(msgs)} messages on 4 channels" in r.output and "the source was cut" in r.output
    with open(fixed, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary.statistics.message_count == len(msgs)
    back = read_messages(fixed)
    assert not back.truncated and [(x.topic, x.msg) for x in back.messages] == msgs
    log.close()
    r = CliRunner().invoke(app, ["repair", str(crashed), "--out", str(crashed)])
    assert r.exit_code == 2 and "is the recording itself" in r.output
def _mixed_recording(path, n: int = 20):
    """States interleaved with the commands a live rig must never get from a replay."""
    with McapLog(path) as log:
        for i in range(n):
            t = int(i * 1e6)
            log.write(keys.state(RIG, "pm"), RobotState(robot="pm", t_s=i * 0.02, state=[float(i)]), log_time_ns=t)
            log.write(keys.cmd(RIG, "pm"), Command(robot="pm", action=[9.0, 9.0]), log_time_ns=t + 1)
            log.write(keys.estop(RIG), EStop(engaged=i % 2 == 0), log_time_ns=t + 2)
            log.write(keys.reset(RIG, "request"), ResetEvent(robot="pm", phase="request"), log_time_ns=t + 3)
            log.write(keys.plan(RIG), Plan(robot="pm", actions=[[0.0, 0.0]]), log_time_ns=t + 4)
            log.write(keys.image(RIG, "cam"), Image(camera="cam", t_s=0.0, width=1, height=1, data=b"abc"),
                      log_time_ns=t + 5)


class _Listener:
    def __init__(self, bus, rig=RIG):
        self.node = Node("listener", rig, bus, handle_signals=False)
        self.sub = self.node.subscribe(keys.all_of(rig), AnyMsg, latest=False)
        self.got: list[tuple[str, object]] = []

    def collect(self, until, timeout_s: float = 10.0):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.got += [(k, decode(p)) for k, p in self.sub.drain()]
            if until(self.got):
                break
            self.sub.wait_queued(0.1)
        return self.got

    def topics(self) -> set[str]:
        return {k for k, _ in self.got}


def test_replay_publishes_only_sensor_and_state_topics_by_default(tmp_path, bus):
    path = tmp_path / "mixed.mcap"
    _mixed_recording(path)
    lis = _Listener(bus)
    try:
        st = replay(path, bus, speed=0)
        lis.collect(lambda g: sum(isinstance(m, RobotState) for _, m in g) >= 20 and
                    sum(isinstance(m, Image) for _, m in g) >= 20)
        time.sleep(0.2)  # anything else in flight would arrive now
        lis.collect(lambda g: False, 0.1)
    finally:
        lis.node.close()
    assert lis.topics() == {keys.state(RIG, "pm"), keys.image(RIG, "cam")}
    assert st.published == 40
    assert st.skipped_commands == {keys.cmd(RIG, "pm"): 20, keys.estop(RIG): 10,
                                   keys.reset(RIG, "request"): 20, keys.plan(RIG): 20}
    assert st.skipped_releases == {keys.estop(RIG): 10}  # the recorded releases: never replayed


def test_replay_include_commands_and_topic_patterns(tmp_path, bus):
    path = tmp_path / "mixed.mcap"
    _mixed_recording(path, n=5)
    lis = _Listener(bus)
    try:
        st = replay(path, bus, speed=0, include_commands=True, topics=["hil/*/pm/*", "hil/*/estop"])
        lis.collect(lambda g: len(g) >= 13)
    finally:
        lis.node.close()
    assert lis.topics() == {keys.state(RIG, "pm"), keys.cmd(RIG, "pm"), keys.estop(RIG)}
    # the 3 engages go out, the 2 releases never do, --include-commands or not
    assert st.published == 13 and st.skipped_by_filter == 15 and not st.skipped_commands
    assert st.skipped_releases == {keys.estop(RIG): 2}
    assert all(m.engaged for _, m in lis.got if isinstance(m, EStop))
    with pytest.raises(ValueError, match="bad topic pattern 'hil//x'"):
        replay(path, bus, topics=["hil//x"])


def test_replay_refuses_a_rig_with_live_driver_nodes_unless_forced(tmp_path, bus):
    path = tmp_path / "mixed.mcap"
    _mixed_recording(path, n=5)
    driver = Node(keys.driver_node("pm"), "live_rig", bus, handle_signals=False)
    lis = _Listener(bus, rig="live_rig")
    try:
        with pytest.raises(ReplayRefused, match="rig 'live_rig' has live driver nodes \\(driver-pm\\)"):
            replay(path, bus, speed=0, rig="live_rig")
        # no window at all: the check still waits for the session's link to the rig (under load a
        # background connect took longer than the window, and a replay went onto a live rig)
        with pytest.raises(ReplayRefused, match="rig 'live_rig' has live driver nodes"):
            replay(path, bus, speed=0, rig="live_rig", live_check_s=0.0)
        time.sleep(0.2)
        assert lis.collect(lambda g: False, 0.2) == []  # nothing was published
        # another rig name is free; --force overrides
        assert replay(path, bus, speed=0, rig="other_rig").published == 10
        assert replay(path, bus, speed=0, rig="live_rig", force=True).published == 10
        lis.collect(lambda g: len(g) >= 10)
        assert lis.topics() == {keys.state("live_rig", "pm"), keys.image("live_rig", "cam")}
    finally:
        lis.node.close()
        driver.close()


def test_record_topics_keeps_the_matching_ones_and_the_specs(tmp_path, bus):
    from hilstack.bus.schemas import SpecMsg, encode

    path = tmp_path / "rec.mcap"
    rec = Recorder(RIG, path, bus, handle_signals=False, topics=[f"hil/{RIG}/*/state"])
    pub = Node("pub", RIG, bus, handle_signals=False)
    try:
        time.sleep(0.5)  # discovery
        pub.session.put(keys.spec(RIG, "pm"), encode(SpecMsg(robot="pm", spec={"state": {"names": ["x"]}})))
        pub.session.put(keys.cmd(RIG, "pm"), encode(Command(robot="pm", action=[1.0], seq=1)))
        pub.session.put(keys.state(RIG, "pm"), encode(RobotState(robot="pm", t_s=0.0, state=[0.0], seq=1)))
        pub.session.put(keys.plan(RIG), encode(Plan(robot="pm", actions=[[0.0]], states=[[0.0]], cost=0.0, seq=1)))
        rec.record(seconds=0.5)
    finally:
        rec.close()
        pub.close()
    back = read_messages(path)
    assert sorted(r.topic for r in back.messages) == [keys.spec(RIG, "pm"), keys.state(RIG, "pm")]
    assert rec.filtered == 2


def test_record_topics_errors_are_one_line(tmp_path):
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    for pattern, why in [("hil/other/*/state", "matches nothing under hil/rec_test/**"),
                         ("hil/**/a**", "bad topic pattern")]:
        r = CliRunner().invoke(app, ["record", "--rig", str(rig_file(tmp_path)), "--out", str(tmp_path / "x.mcap"),
                                     "--topics", pattern])
        assert r.exit_code == 2 and why in r.output and r.output.strip().count("\n") == 0, r.output
        assert not (tmp_path / "x.mcap").exists()
