"""Short fuzzing of every parser of untrusted bytes (the long runs: `hil bench fuzz`).

The harnesses and their invariants live in tools/fuzz.py; here hypothesis drives them
with a few hundred inputs per parser (random bytes and mutated valid frames), and a short
atheris run checks the runner, including that it reports a crash.
"""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hilstack.bus import schemas
from hilstack.tools import fuzz

SETTINGS = settings(max_examples=300, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow])


def mutated(seeds: list[bytes]) -> st.SearchStrategy[bytes]:
    """A valid input with a few bytes replaced, inserted or cut: deeper than random bytes."""

    def mutate(seed: bytes, edits: list[tuple[int, int, int]], cut: int) -> bytes:
        b = bytearray(seed)
        for kind, pos, val in edits:
            i = pos % (len(b) + 1)
            if kind == 0 and i < len(b):
                b[i] = val
            elif kind == 1:
                b.insert(i, val)
            elif i < len(b):
                del b[i]
        return bytes(b[: len(b) - cut % 8]) if cut % 3 == 0 else bytes(b)

    edit = st.tuples(st.integers(0, 2), st.integers(0, 1023), st.integers(0, 255))
    return st.builds(mutate, st.sampled_from(seeds), st.lists(edit, max_size=6), st.integers(0, 255))


def inputs(target: str) -> st.SearchStrategy[bytes]:
    _, seeds, _ = fuzz.TARGETS[target]
    return st.one_of(st.binary(max_size=300), mutated(seeds()))


@pytest.mark.parametrize("target", sorted(fuzz.TARGETS))
def test_the_seeds_are_valid_input(target):
    harness, seeds, _ = fuzz.TARGETS[target]
    for s in seeds():
        harness(s)


def test_seeds_reach_past_the_checks():
    """The seeds decode to real frames and messages, so mutations start deep in the parser."""
    from hilstack.drivers.velociroach.link import XBeeDeframer
    from hilstack.drivers.velociroach.mavlink import MavDecoder

    d = XBeeDeframer()
    assert sum(len(d.feed(s[2:], now_s=0.0)) for s in fuzz.seeds_xbee()) >= 20
    dec = MavDecoder()
    assert all(dec.decode(s[2:]) is not None for s in fuzz.seeds_mavlink()[:-1])
    for s in fuzz.seeds_bus():
        schemas.decode(s[1:], fuzz._bus_types()[s[0]])


@SETTINGS
@given(inputs("xbee"))
def test_fuzz_xbee_deframer(data):
    fuzz.fuzz_xbee(data)


@SETTINGS
@given(inputs("mavlink"))
def test_fuzz_mavlink_decoder(data):
    fuzz.fuzz_mavlink(data)


@SETTINGS
@given(inputs("bus"))
def test_fuzz_bus_decoders(data):
    fuzz.fuzz_bus(data)


def test_a_non_utf8_string_is_a_malformed_message():
    """Found by `hil bench fuzz`: msgspec let UnicodeDecodeError out of hilstack.bus.schemas.decode."""
    raw = bytes.fromhex("84a474797065aa68696c2e50696e0884a47479672f31")  # a Ping with a broken tag
    with pytest.raises(schemas.MalformedMessage):
        schemas.decode(raw, schemas.Ping)
    good = schemas.encode(schemas.Command(robot="roach", action=[0.0, 0.0]))
    bad = good.replace(b"roach", b"ro\xffch")
    with pytest.raises(schemas.MalformedMessage, match="Command"):
        schemas.decode(bad, schemas.Command)


def test_the_mavlink_crc_fixer_makes_a_flipped_frame_decode():
    from hilstack.drivers.velociroach.mavlink import MavDecoder

    frame = bytearray(fuzz._mav_seed_frames()[4])
    frame[14] ^= 0x10  # a payload bit: the CRC no longer matches
    dec = MavDecoder()
    assert dec.decode(bytes(frame)) is None and dec.corrupt == 1
    assert dec.decode(fuzz.fix_mavlink_crc(bytes(frame))) is not None


def test_a_broken_counter_is_caught_by_the_harness(monkeypatch):
    """Break the deframer's bookkeeping on purpose: the harness must call it a crash."""
    from hilstack.drivers.velociroach.link import XBeeDeframer

    def bad_without_kind(self, kind, why):  # counts the total but forgets the kind
        self.corrupt += 1
        self.last_error = why

    seed = fuzz.seeds_xbee()[1]  # starts with garbage
    fuzz.fuzz_xbee(seed)
    monkeypatch.setattr(XBeeDeframer, "_bad", bad_without_kind)
    with pytest.raises(fuzz.InvariantBroken, match="kinds add up"):
        fuzz.fuzz_xbee(seed)


def test_a_decoder_that_loses_count_is_caught(monkeypatch):
    from hilstack.drivers.velociroach.mavlink import MavDecoder

    monkeypatch.setattr(MavDecoder, "_fail", lambda self, why: None)
    with pytest.raises(fuzz.InvariantBroken, match="frames decoded"):
        fuzz.fuzz_mavlink(b"\x00\x10" + b"\xfd" * 40)


def planted_bug(data: bytes) -> None:
    """A parser with a crash the fuzzer must find (used by the runner test below)."""
    if len(data) >= 2 and data[0] == 0x7E:
        raise IndexError("planted bug")


def test_the_atheris_runner_counts_inputs_and_reports_a_crash():
    clean = fuzz.run_target("bus", 3000)
    assert clean["crashes"] == 0 and clean["inputs"] == 3000 and "crash" not in clean
    found = fuzz.run_target("tests.test_fuzz:planted_bug", 200_000)
    assert found["crashes"] == 1
    assert found["crash"]["exception"][0] == "IndexError: planted bug"
    assert found["crash"]["input_hex"].startswith("7e")


def test_unknown_target_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown fuzz target 'nope'"):
        fuzz.resolve("nope")


# --------------------------------------------------------------------------- configs and arguments
CONFIG_TARGETS = ["robot_config", "rig_config", "reset_config", "task_config", "cli_args"]
QUICK = settings(max_examples=120, deadline=None, derandomize=True, database=None,
                 suppress_health_check=[HealthCheck.too_slow])


@pytest.mark.parametrize("target", CONFIG_TARGETS)
def test_fuzz_config_loaders_and_arguments(target):
    """Generated robot, rig, reset and task configs and `hil` argument lists: each loads,
    or is one ConfigError line naming the file and field (exit 2); nothing else escapes,
    and nothing that loads carries a non-finite or unbounded safety value."""
    harness = fuzz.TARGETS[target][0]

    @QUICK
    @given(st.binary(min_size=16, max_size=300))
    def run(data):
        harness(data)

    run()


def test_the_generated_configs_reach_the_robots():
    """The generator is not stuck at the schema's door: many documents load and build a
    driver of every robot (so the spec checks run), many others are refused."""
    import random

    from hilstack.tools import fuzz_configs as fc

    built, refused = set(), 0
    real_build, real_err = fc.check_spec, fc.check_config_error

    def spec(drv):
        built.add(drv.spec.name)
        real_build(drv)

    def err(e, f):
        nonlocal refused
        refused += 1
        real_err(e, f)

    rng = random.Random(0)
    fc.check_spec, fc.check_config_error = spec, err
    try:
        for _ in range(400):
            fc.fuzz_robot_config(bytes(rng.getrandbits(8) for _ in range(200)))
    finally:
        fc.check_spec, fc.check_config_error = real_build, real_err
    assert refused > 50 and {"pointmass", "velociroach", "shadow_hand", "widowx", "sawyer", "camera"} <= built, built


def test_the_config_harness_catches_what_it_must(monkeypatch):
    """Break-it: a loader that lets a TypeError out, a multi-line error, an unbounded
    period that loads, a non-finite argument that reaches a verb: each is a crash."""
    from hilstack.configs import schema
    from hilstack.tools import common, fuzz_configs

    doc = b"\x00" * 64  # past-the-end choices: a plain pointmass config

    def boom(*a, **k):
        raise TypeError("planted")

    monkeypatch.setattr(schema, "robot_config", boom)
    with pytest.raises(TypeError, match="planted"):
        fuzz_configs.fuzz_robot_config(doc)
    monkeypatch.undo()

    err = schema.ConfigError("/x.yaml", [("params.a", "bad")])
    err.problems = [("params.a", "two\nlines")]
    with pytest.raises(fuzz.InvariantBroken, match="not one line"):
        fuzz_configs.check_config_error(err, "/x.yaml")

    import dataclasses
    import types

    from hilstack.drivers.registry import make_driver

    drv = make_driver(schema.robot_config({"robot": "pointmass"}, "/x.yaml"))
    fuzz_configs.check_spec(drv)
    slow = types.SimpleNamespace(spec=dataclasses.replace(drv.spec, period_s=1e9))  # what `period_s: 1e9` made
    with pytest.raises(fuzz.InvariantBroken, match="period_s"):
        fuzz_configs.check_spec(slow)

    monkeypatch.setattr(common, "check_args", lambda params: None)
    cmd, ctx = fuzz_configs.parse_argv(["estop", "r", "--timeout-s", "inf"])
    assert ctx.params["timeout_s"] == float("inf")  # click parses it: the check is ours
    with pytest.raises(fuzz.InvariantBroken, match="timeout_s=inf reaches the verb"):
        fuzz_configs.fuzz_cli_args_argv(["estop", "r", "--timeout-s", "inf"])


def test_a_non_finite_argument_is_one_line_exit_2():
    """Found by the cli_args fuzzer: `hil estop RIG --timeout-s inf` parsed, and the e-stop
    waited forever for acknowledgements; every verb now refuses non-finite numbers."""
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    for args in (["drive", "pointmass", "--seconds", "nan"], ["bench", "tracker", "--seconds", "-inf"],
                 ["estop", "r", "--timeout-s", "inf"]):
        r = CliRunner().invoke(app, args)
        assert r.exit_code == 2 and "expected a finite number" in r.output, (args, r.output)
        assert len([ln for ln in r.output.splitlines() if ln.strip()]) == 1


def test_a_nonfinite_value_under_an_empty_key_names_its_field():
    """Found by `hil bench fuzz --target task_config` (input b9b936b9903636363636): a task's
    free key '' holding inf gave an error with an empty field; the field is now ''."""
    from hilstack.configs.schema import ConfigError, task_config
    from hilstack.tools import fuzz_configs

    fuzz_configs.fuzz_task_config(bytes.fromhex("b9b936b9903636363636"))
    with pytest.raises(ConfigError) as e:
        task_config({"task": "x", "": float("inf")}, "/t.yaml")
    assert e.value.problems == [("''", "expected a finite number (got inf)")]


@pytest.mark.parametrize(("target", "hexed"), [
    # the reset mechanism's rotate_half_range_deg: 1e-300 collapsed its action range to 0 (both rig and robot)
    ("robot_config", "9494949429949494949191919191919191919191919191919191919191919191919191919191919191919191919191"
                     "919191919191919191919191"),
    ("rig_config", "5555555555555555555555555555555555555555555555555555555555555555555555555555555555555555555555"
                   "5555555555555555555555555555555555555555555555552525252525252525252525252525252525252525252525"
                   "25252525252525252525252525252525252525dededededede252525"),
    # a recursive YAML alias: RecursionError in the task's finite-number check
    ("task_config", "4ac0b67d7d7d7d7d7d7d7d7d7d7d7d7d7d7d7d4a"),
])
def test_what_hil_bench_fuzz_found_in_the_configs(target, hexed):
    """Found by the 100k-input runs of `hil bench fuzz` (docs/platform.md, "Fuzzing")."""
    fuzz.TARGETS[target][0](bytes.fromhex(hexed))


def test_recursive_and_exploding_yaml_is_one_error(tmp_path):
    from hilstack.configs.schema import ConfigError, load_robot

    bomb = "a: &a [1,1,1,1,1,1,1,1,1,1]\n" + "".join(
        f"{n}: &{n} [{', '.join([f'*{p}'] * 10)}]\n" for p, n in zip("abcd", "bcde", strict=True))
    for text, why in (("robot: pointmass\nparams: &p {x: *p}\n", "recursive alias"),
                      ("robot: pointmass\n" + bomb, "expand past 100000 nodes")):
        p = tmp_path / "r.yaml"
        p.write_text(text)
        with pytest.raises(ConfigError, match=f"{p}: <root>: not valid YAML for a config: .*{why}"):
            load_robot(p)
