"""The bus form of a model update (bus/schemas.py ModelUpdate): tensors as raw float32,
validated on the way in, and recorded to MCAP like every other message."""

from __future__ import annotations

import numpy as np
import pytest

from hilstack.bus import keys
from hilstack.bus.recording import McapLog, iter_messages
from hilstack.bus.schemas import MalformedMessage, ModelUpdate, TaskPosterior, decode, encode, json_schema

W = {"net.0.weight": np.arange(6, dtype=np.float32).reshape(2, 3) / 7, "net.0.bias": np.array([0.5, -1.0])}
EXPECTED = {"net.0.weight": (2, 3), "net.0.bias": (2,)}


def test_tensors_round_trip_bit_exact_over_the_wire():
    m = ModelUpdate.pack(W, method="mb_de", update_seq=4, state_stamp_ns=123, info={"loss": 0.5})
    back = decode(encode(m), ModelUpdate)
    t = back.tensors(EXPECTED)
    assert list(t) == list(W)
    for k, v in W.items():
        np.testing.assert_array_equal(t[k], v.astype(np.float32))
        assert t[k].dtype == np.float32
    assert back.state_stamp_ns == 123 and back.info == {"loss": 0.5}
    # the payload is the raw buffer plus a small header, not a number-by-number encoding
    assert len(encode(m)) < 8 * 4 + 200


@pytest.mark.parametrize(
    ("change", "error"),
    [
        (lambda m: setattr(m, "data", m.data[:-4]), "bytes of float32"),
        (lambda m: setattr(m, "shapes", [[3, 2], [2]]), r"shape \(3, 2\), the model expects \(2, 3\)"),
        (lambda m: setattr(m, "names", ["net.0.weight", "net.9.bias"]), "unknown tensor 'net.9.bias'"),
        (lambda m: setattr(m, "names", ["net.0.weight"]), "1 names but 2 shapes"),
        (lambda m: setattr(m, "kind", "everything"), "kind 'everything'"),
        (lambda m: setattr(m, "shapes", [[2, -3], [2]]), "out of range"),
    ],
)
def test_bad_tensors_are_one_line_errors(change, error):
    m = ModelUpdate.pack(W, method="grbal")
    change(m)
    with pytest.raises(MalformedMessage, match=error) as e:
        decode(encode(m), ModelUpdate).tensors(EXPECTED)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values_name_the_tensor(bad):
    w = {k: v.copy().astype(np.float32) for k, v in W.items()}
    w["net.0.bias"][1] = bad
    with pytest.raises(MalformedMessage, match="'net.0.bias' has NaN or inf"):
        ModelUpdate.pack(w, method="grbal").tensors()


def test_subset_and_context_need_not_carry_every_tensor_but_full_does():
    sub = ModelUpdate.pack({"net.0.bias": W["net.0.bias"]}, method="grbal", kind="subset")
    assert list(sub.tensors(EXPECTED)) == ["net.0.bias"]
    full = ModelUpdate.pack({"net.0.bias": W["net.0.bias"]}, method="grbal", kind="full")
    with pytest.raises(MalformedMessage, match=r"lacks tensors \['net.0.weight'\]"):
        full.tensors(EXPECTED)


def test_update_and_posterior_are_recorded_and_read_back(tmp_path):
    m = ModelUpdate.pack(W, method="mole", update_seq=2, state_stamp_ns=99, info={"tasks": 2})
    p = TaskPosterior(method="mole", update_seq=2, posterior=[0.2, 0.8], task=1, tasks_created=2)
    with McapLog(tmp_path / "a.mcap") as log:
        log.write(keys.model_update("r"), m)
        log.write(keys.task_posterior("r"), p)
    got = {rm.topic: rm.msg for rm in iter_messages(tmp_path / "a.mcap")}
    assert got[keys.task_posterior("r")].posterior == [0.2, 0.8]
    back = got[keys.model_update("r")]
    np.testing.assert_array_equal(back.tensors(EXPECTED)["net.0.weight"], W["net.0.weight"].astype(np.float32))
    # JSON recording: bytes as base64, declared so in the schema third-party tools read
    assert json_schema(ModelUpdate)["properties"]["data"]["contentEncoding"] == "base64"


def test_task_posterior_is_plotted_per_task_in_rerun(tmp_path):
    import rerun as rr
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    mc = tmp_path / "a.mcap"
    with McapLog(mc) as log:
        for i in range(5):
            log.write(keys.task_posterior("r"), TaskPosterior(method="mole", update_seq=i, posterior=[0.9, 0.1],
                                                              task=0, tasks_created=2))
    rrd = tmp_path / "a.rrd"
    r = CliRunner().invoke(app, ["viz", "--recording", str(mc), "--save", str(rrd)])
    assert r.exit_code == 0, r.output
    ents = {str(c.entity_path) for c in rr.chunk.RrdReader(str(rrd)).stream().to_chunks()}
    assert {"/model/mole/posterior/task0", "/model/mole/posterior/task1"} <= ents
