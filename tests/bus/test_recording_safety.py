"""Issue 22, items 13 and 14: recordings are never lost, overwritten or misread.

- A file that is not MCAP (empty, random bytes, a CSV) is refused with one line, exit 2,
  by inspect / replay / repair, and repair writes nothing.
- Every cut point of a small real recording is either repaired (keeping every message of
  the chunks completed before the cut) or refused with one line: never a traceback.
- `hil record` / `hil repair` never overwrite an existing file without --force, and an
  output they cannot write is one line, exit 2, without hanging (real subprocesses, bounded
  waits).
"""

from __future__ import annotations

import struct

import pytest
from typer.testing import CliRunner

from hilstack.bus import keys
from hilstack.bus.recording import (
    MCAP_MAGIC,
    McapLog,
    NotARecording,
    RecordingExists,
    check_mcap,
    read_messages,
    repair,
)
from hilstack.bus.schemas import RobotState, SpecMsg
from hilstack.tools.cli import app

RIG = "rec_safety"
#: a verb that has failed must have exited by then (a hang shows as a timeout) [s]
EXIT_BOUND_S = 60.0


def _small_recording(path) -> bytes:
    """A spec, six states (the Foxglove pose channels derived from them) in three chunks,
    each followed by its message indexes, then the summary: every kind of record."""
    with McapLog(path) as log:
        log.write(keys.spec(RIG, "pm"), SpecMsg(robot="pm", spec={"state": {"names": ["x", "y", "yaw"]}}, seq=1))
        for i in range(6):
            log.write(keys.state(RIG, "pm"), RobotState(robot="pm", t_s=i * 0.1, state=[float(i), 0.0, 0.1],
                                                        seq=i + 1, stamp_s=1000.0 + i))
            if i % 2 == 1:
                log.flush()  # closes the chunk: its message indexes follow it
    return path.read_bytes()


def _records(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, start, end) of each top-level record, from the MCAP framing (opcode u8,
    length u64), independently of the mcap package."""
    out, off = [], len(MCAP_MAGIC)
    while off + 9 <= len(data):
        op, ln = data[off], struct.unpack_from("<Q", data, off + 1)[0]
        out.append((op, off, off + 9 + ln))
        off += 9 + ln
    return out


def _chunk_ends_and_counts(data: bytes) -> list[tuple[int, int]]:
    """(end offset, messages in it) of each Chunk record (opcode 0x06), decoded by hand."""
    import zstandard

    out = []
    for op, start, end in _records(data):
        if op != 0x06:
            continue
        body = data[start + 9:end]
        usize = struct.unpack_from("<Q", body, 16)[0]
        p = 28  # start, end times (u64), uncompressed size (u64), crc (u32)
        clen = struct.unpack_from("<I", body, p)[0]
        comp = body[p + 4:p + 4 + clen].decode()
        p += 4 + clen
        rlen = struct.unpack_from("<Q", body, p)[0]
        raw = body[p + 8:p + 8 + rlen]
        if comp == "zstd":
            raw = zstandard.ZstdDecompressor().decompress(raw, max_output_size=usize)
        n, q = 0, 0
        while q < len(raw):
            n += raw[q] == 0x05  # Message
            q += 9 + struct.unpack_from("<Q", raw, q + 1)[0]
        out.append((end, n))
    return out


def _finished_count(path) -> int:
    """Messages of a finished file through the reader that needs its summary (as rerun does)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        r = make_reader(f)
        assert r.get_summary() is not None
        return sum(1 for _ in r.iter_messages())


def test_every_cut_point_is_repaired_or_refused(tmp_path, monkeypatch):
    """The review cut 3 of 25 points inside a MessageIndex record and got struct.error:
    here every byte boundary of a small recording is tried."""
    import os

    monkeypatch.setattr(os, "fsync", lambda fd: None)  # durability is not what this checks: 6000 repairs
    data = _small_recording(tmp_path / "src.mcap")
    chunks = _chunk_ends_and_counts(data)
    assert len(chunks) == 3 and sum(n for _, n in chunks) == _finished_count(tmp_path / "src.mcap")
    assert any(op == 0x07 for op, _, _ in _records(data))  # MessageIndex records are cut too
    cut_file, out = tmp_path / "cut.mcap", tmp_path / "out.mcap"
    for cut in range(len(data) + 1):
        cut_file.write_bytes(data[:cut])
        out.unlink(missing_ok=True)
        if cut < len(MCAP_MAGIC):
            with pytest.raises(NotARecording):
                read_messages(cut_file)
            with pytest.raises(NotARecording):
                repair(cut_file, out)
            assert not out.exists(), f"cut {cut}: repair wrote a file for a non-recording"
            continue
        back = read_messages(cut_file)  # never raises: stops at the damage
        r = repair(cut_file, out)
        complete = sum(n for end, n in chunks if end <= cut)
        assert r.messages == complete, f"cut {cut}: repaired {r.messages} of {complete} complete messages"
        assert _finished_count(out) == complete, f"cut {cut}"
        assert len(back.messages) == len(read_messages(out).messages), f"cut {cut}"
        assert r.truncated == (cut < len(data)), f"cut {cut}"


def test_cut_points_through_the_cli_are_one_line(tmp_path):
    """`hil inspect` / `hil repair` on cut files (every point of the first MessageIndex
    record, and a stride through the rest): exit 0 with the damage named, or exit 2 with
    one line; never a traceback."""
    data = _small_recording(tmp_path / "src.mcap")
    first_index = next((s, e) for op, s, e in _records(data) if op == 0x07)
    cuts = sorted(set(range(*first_index)) | set(range(0, len(data) + 1, 37)) | {1, 7, 8, 9})
    cut_file = tmp_path / "cut.mcap"
    for cut in cuts:
        cut_file.write_bytes(data[:cut])
        out = tmp_path / f"fixed-{cut}.mcap"
        for args in (["inspect", str(cut_file)], ["repair", str(cut_file), "--out", str(out)]):
            r = CliRunner().invoke(app, args)
            assert r.exception is None or isinstance(r.exception, SystemExit), (cut, args, r.exception)
            assert "Traceback" not in r.output
            if cut < len(MCAP_MAGIC):
                assert r.exit_code == 2 and "is not an MCAP recording" in r.output, (cut, r.output)
                assert r.output.strip().count("\n") == 0, r.output
            else:
                assert r.exit_code == 0, (cut, args, r.output)
        assert (cut >= len(MCAP_MAGIC)) == out.exists(), cut


@pytest.mark.parametrize("content", [b"", b"x,y\n1,2\n3,4\n", bytes(range(256)) * 4], ids=["empty", "csv", "random"])
def test_not_mcap_is_refused_in_one_line_and_nothing_is_written(tmp_path, content):
    src = tmp_path / "data.mcap"
    src.write_bytes(content)
    with pytest.raises(NotARecording):
        check_mcap(src)
    out = tmp_path / "fixed.mcap"
    for args in (["inspect", str(src)], ["inspect", str(src), "--json"], ["replay", str(src), "--speed", "0"],
                 ["repair", str(src), "--out", str(out)],
                 ["viz", "--recording", str(src), "--save", str(tmp_path / "v.rrd")]):
        r = CliRunner().invoke(app, args)
        assert r.exit_code == 2, (args, r.output)
        assert "is not an MCAP recording" in r.output and r.output.strip().count("\n") == 0, (args, r.output)
    assert not out.exists() and not (tmp_path / "v.rrd").exists()
    assert src.read_bytes() == content


def test_repair_never_overwrites_without_force(tmp_path):
    _small_recording(tmp_path / "src.mcap")
    out = tmp_path / "kept.mcap"
    out.write_bytes(b"an earlier repair, or anything else")
    with pytest.raises(RecordingExists):
        repair(tmp_path / "src.mcap", out)
    r = CliRunner().invoke(app, ["repair", str(tmp_path / "src.mcap"), "--out", str(out)])
    assert r.exit_code == 2 and "exists: not overwritten" in r.output, r.output
    assert out.read_bytes() == b"an earlier repair, or anything else"
    assert not [p for p in tmp_path.iterdir() if p.suffix == ".part"]  # no temporary left behind
    r = CliRunner().invoke(app, ["repair", str(tmp_path / "src.mcap"), "--out", str(out), "--force"])
    assert r.exit_code == 0, r.output
    assert _finished_count(out) == _finished_count(tmp_path / "src.mcap")
    r = CliRunner().invoke(app, ["repair", str(tmp_path / "src.mcap"), "--out", str(tmp_path)])
    assert r.exit_code == 2 and "is a directory" in r.output, r.output


def test_mcap_log_refuses_an_existing_file_when_asked(tmp_path):
    p = tmp_path / "a.mcap"
    p.write_bytes(b"precious")
    with pytest.raises(RecordingExists):
        McapLog(p, overwrite=False)
    assert p.read_bytes() == b"precious"


def _rig_file(tmp_path):
    p = tmp_path / f"{RIG}.yaml"
    p.write_text(f"name: {RIG}\nrobots:\n  pm:\n    config: pointmass\n    backend: sim\n")
    return p


def _run(spawn, *args: str):
    """A `hil` subprocess that must end on its own within EXIT_BOUND_S: (code, stderr)."""
    import subprocess

    pr = spawn(*args)
    try:
        pr.p.wait(EXIT_BOUND_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"hil {' '.join(args)} still running after {EXIT_BOUND_S:g} s (hangs)")
    return pr.p.returncode, pr.p.stderr.read()


def test_record_out_errors_are_one_line_and_do_not_hang(tmp_path, bus, spawn):
    """--out an existing recording, a directory, or a file that cannot be created: exit 2,
    one line, the process ends (the review saw the last two print their error and hang),
    the existing file untouched."""
    rig = str(_rig_file(tmp_path))
    existing = tmp_path / "yesterday.mcap"
    _small_recording(existing)
    before = existing.read_bytes()
    (tmp_path / "adir").mkdir()
    for out, why in [(existing, "exists: not overwritten"), (tmp_path / "adir", "is a directory"),
                     ("/proc/x.mcap", "cannot write it")]:
        code, err = _run(spawn, "record", "--rig", rig, "--out", str(out), "--seconds", "1",
                         "--endpoint", bus.endpoint)
        assert code == 2 and why in err, (out, code, err)
        assert "Traceback" not in err and err.strip().count("\n") == 0, err
    assert existing.read_bytes() == before


def test_record_force_replaces_and_warns_when_no_node_is_alive(tmp_path, bus, spawn):
    """--force replaces an existing file; a rig with no node alive gets a warning (the
    recording goes on, exit 0)."""
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"old")
    code, err = _run(spawn, "record", "--rig", str(_rig_file(tmp_path)), "--out", str(existing), "--force",
                     "--seconds", "8", "--endpoint", bus.endpoint)
    assert code == 0, err
    assert f"no node alive on rig {RIG}" in err, err
    check_mcap(existing)
    assert not read_messages(existing).truncated


def test_record_mistyped_rig_is_an_error(tmp_path, spawn):
    code, err = _run(spawn, "record", "--rig", "pointmass_simm", "--out", str(tmp_path / "r.mcap"),
                     "--seconds", "1")
    assert code == 2 and "no such rig config" in err and "pointmass_simm" in err, err
    assert not (tmp_path / "r.mcap").exists()


@pytest.mark.parametrize("args, why", [
    (["record", "--rig", "pointmass_sim", "--seconds", "nan"], "--seconds"),
    (["record", "--rig", "pointmass_sim", "--seconds", "-1"], "--seconds"),
    (["replay", "REC", "--speed", "nan"], "--speed"),
    (["replay", "REC", "--speed", "inf"], "--speed"),
    (["replay", "REC", "--rig", "a/b"], "no such rig config"),
    (["nodes", "a/b"], "no such rig config"),
    (["estop", "a/b"], "no such rig config"),
    (["foxglove", "--rig", "a/b"], "no such rig config"),
    (["viz", "--rig", "a/b", "--seconds", "1"], "no such rig config"),
])
def test_bad_cli_values_are_one_line_exit_2(tmp_path, args, why):
    rec = tmp_path / "r.mcap"
    _small_recording(rec)
    args = [str(rec) if a == "REC" else a for a in args]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2 and why in r.output, (args, r.exit_code, r.output, r.exception)
    assert r.output.strip().count("\n") == 0, r.output
