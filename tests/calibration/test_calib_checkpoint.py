"""The ``checkpoint`` nominal model: a learned dynamics checkpoint, where an effect is a missing input.

System (hilstack.calibration.synthetic_learned): a 1-D point mass whose actuation is one period late
(the next state depends on a_{t-1}) or whose force scales with a sagging battery voltage. The
checkpoint is a small EnsembleDynamics (2 members, 2x64) trained on (s_t, a_t) only.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from hilstack.calibration import DataError, ModelNotAvailable, get_model, load_model, run_calibration
from hilstack.calibration.learned import CheckpointError, load_augmented
from hilstack.calibration.selection import SelectionConfig
from hilstack.calibration.synthetic_learned import generate, train_checkpoint, write_csv
from hilstack.tools.cli import app
from tests.helpers import spec_dict

# The tests check behaviour, not tight intervals: fewer bootstrap replicates and short retrains.
CFG = SelectionConfig(n_boot=12)
OPTS = {"epochs": 25}
runner = CliRunner()


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    torch.set_num_threads(1)
    return train_checkpoint(tmp_path_factory.mktemp("ckpt") / "model.pt", n_episodes=30, epochs=30)


@pytest.fixture(scope="module")
def delay_run(ckpt, tmp_path_factory):
    out = tmp_path_factory.mktemp("delay")
    eps = generate(20, 80, hidden="delay", seed=1)
    rep = run_calibration(eps, model=str(ckpt), out_dir=out, seed=0, progress=False, plots=False, config=CFG,
                          model_options=OPTS)
    return rep, out


def test_delay_accepts_lagged_action(delay_run):
    rep, _ = delay_run
    assert rep["verdict"] == "found"
    names = [e["name"] for e in rep["effects"]]
    assert names[0] == "action_lag1", names
    e = rep["effects"][0]
    assert e["heldout_gain"] > 0.5 and e["p_value"] < 0.01
    assert e["interval"][0] > 0.0  # shuffling a_{t-1} out of bag hurts in every replicate
    # the wrong candidates do not pass
    assert not {"vbat", "time_since_reset"} & set(names)


def test_delay_multi_step_error_falls(delay_run):
    rep, _ = delay_run
    before, after = rep["before"]["multi_step_nrmse"], rep["after"]["multi_step_nrmse"]
    assert after["mean"] < 0.5 * before["mean"]
    assert after["mean_interval"][1] < before["mean_interval"][0]
    assert rep["after"]["one_step_nrmse"]["mean"] < 0.5 * rep["before"]["one_step_nrmse"]["mean"]
    assert set(before["per_channel"]) == {"x", "v"}


def test_augmented_model_saved_and_reloadable(delay_run):
    rep, out = delay_run
    am = rep["augmented_model"]
    assert am["path"].endswith("model_augmented.pt") and (out / "model_augmented.pt").exists()
    assert am["extra_inputs"][0]["name"] == "action_lag1" and am["extra_inputs"][0]["columns"] == ["u_lag1"]
    assert am["extra_inputs"][0]["action_index"] == [1, 2]
    aug = load_augmented(out / "model_augmented.pt")
    assert aug.effects == [e["name"] for e in rep["effects"]] and aug.action_names == ["u"]
    assert load_model(out / "model.json").effects == aug.effects
    # fresh data from the delayed system: the reloaded model replays it far better than the checkpoint
    fresh = generate(3, 80, hidden="delay", seed=77)
    plain = load_augmented(rep["augmented_model"]["checkpoint"])
    assert plain.effects == []
    err_aug, err_ck = [], []
    for e in fresh:
        s, a = e.states, e.actions[:-1]
        # velocity: the whole-episode position replay also integrates any small velocity bias
        err_aug.append(np.mean((aug.rollout(s, a, e.t_s, e.vbat_v) - s)[:, 1] ** 2))
        err_ck.append(np.mean((plain.rollout(s, a) - s)[:, 1] ** 2))
        ex = torch.from_numpy(aug.features(s, a, e.t_s, e.vbat_v))
        nxt = aug.predict(torch.from_numpy(s[:-1]).float(), torch.from_numpy(a).float(), ex)
        assert nxt.shape == (2, 80, 2)
    assert np.mean(err_aug) < 0.5 * np.mean(err_ck), (err_aug, err_ck)
    with pytest.raises(ValueError, match="columns"):
        aug.predict(torch.zeros(1, 2), torch.zeros(1, 1), torch.zeros(1, 5))


def test_no_hidden_dependence_finds_nothing(ckpt, tmp_path):
    eps = generate(20, 80, hidden="none", seed=2)
    rep = run_calibration(eps, model=str(ckpt), out_dir=tmp_path, seed=0, progress=False, plots=False, config=CFG,
                          model_options=OPTS)
    assert rep["verdict"] == "none" and rep["effects"] == []
    assert rep["augmented_model"]["extra_inputs"] == []
    assert rep["after"]["multi_step_nrmse"]["mean"] == rep["before"]["multi_step_nrmse"]["mean"]
    assert all(abs(c["heldout_gain"]) < 0.05 for c in rep["rounds"][0]["candidates"])


def test_cli_vbat_from_csv(ckpt, tmp_path):
    """A CSV whose columns are named differently from the checkpoint's channels, through --map."""
    csv = write_csv(generate(20, 80, hidden="vbat", seed=3), tmp_path / "log.csv")
    out = tmp_path / "out"
    res = runner.invoke(app, ["calibrate", "--data", str(csv), "--model", str(ckpt), "--map",
                              "x=pos_m,v=vel_mps,u=cmd,t=time,vbat=vbat_v", "--epochs", "25", "--out", str(out),
                              "--seed", "0", "--json", "--quiet"])
    assert res.exit_code == 0, res.output
    line = json.loads(res.stdout.strip().splitlines()[-1])
    assert line["verdict"] == "found" and line["effects"][0]["name"] == "vbat"
    assert line["effects"][0]["heldout_gain"] > 0.1
    assert line["after_multi_step_nrmse"] < line["before_multi_step_nrmse"]
    for f in ("report.json", "report.md", "model.json", "model_augmented.pt", "residual_before_after.png",
              "candidates.png"):
        assert (out / f).exists(), f
    rep = json.loads((out / "report.json").read_text())
    assert rep["augmented_model"]["extra_inputs"][0]["columns"] == ["vbat_v"]
    assert "Augmented model" in (out / "report.md").read_text()


def test_cli_checkpoint_option_and_errors(ckpt, tmp_path):
    csv = write_csv(generate(12, 40, seed=4), tmp_path / "log.csv")
    # missing checkpoint
    res = runner.invoke(app, ["calibrate", "--data", str(csv), "--model", str(tmp_path / "nope.pt"),
                              "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "checkpoint not found" in res.output and "Traceback" not in res.output
    # a file that is not a dynamics checkpoint
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    res = runner.invoke(app, ["calibrate", "--data", str(csv), "--model", "checkpoint", "--checkpoint", str(junk),
                              "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "not a dynamics checkpoint" in res.output
    res = runner.invoke(app, ["calibrate", "--data", str(csv), "--model", "checkpoint", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "--checkpoint" in res.output
    # channels not matching the checkpoint's names: the missing ones are named
    res = runner.invoke(app, ["calibrate", "--data", str(csv), "--model", str(ckpt), "--map", "t=time,x=pos_m",
                              "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "('v', 'v')" in res.output and "('u', 'u')" in res.output
    assert "'x'" not in res.output.split("columns:")[0].split("checkpoint's")[1]


def test_errors_python_api(ckpt, tmp_path):
    with pytest.raises(ModelNotAvailable, match="not available"):
        get_model("checkpoint")
    with pytest.raises(CheckpointError, match="not found"):
        get_model(str(tmp_path / "missing.pt"))
    assert isinstance(get_model(str(ckpt)).name, str)
    with pytest.raises(DataError, match="too few episodes: 5"):
        run_calibration(generate(5, 40, seed=5), model=str(ckpt), out_dir=tmp_path, progress=False, plots=False)
    eps = generate(12, 40, seed=5)
    renamed = [type(e)(**{**e.__dict__, "state_names": ("pos", "v")}) for e in eps]
    with pytest.raises(DataError, match=r"state channels \['x'\]"):
        run_calibration(renamed, model=str(ckpt), out_dir=tmp_path, progress=False, plots=False)


def _write_mcap(episodes, path, high: float):
    from hilstack.bus import keys
    from hilstack.bus.recording import McapLog
    from hilstack.bus.schemas import RobotState, SpecMsg

    spec = spec_dict("mass", ["x", "v", "vbat"], ["u"], -high, high)
    seq, t_base = 0, 0.0
    with McapLog(path) as log:
        log.write(keys.spec("calib", "mass"), SpecMsg(robot="mass", spec=spec, seq=1))
        for i, e in enumerate(episodes):
            for k in range(e.n):
                seq += 1
                t = t_base + float(e.t_s[k])
                log.write(keys.state("calib", "mass"), RobotState(
                    robot="mass", t_s=t, state=[*map(float, e.states[k]), float(e.vbat_v[k])],
                    action=[] if k == 0 else [float(e.actions[k - 1, 0])], episode=i, seq=seq, stamp_s=1000.0 + t,
                    active=True))
            t_base += float(e.t_s[-1]) + 1.0
    return path


def test_mcap_channels_matched_by_name_and_actions_normalized(ckpt, tmp_path):
    """An MCAP recording: channels by name (the extra 'vbat' state becomes the vbat candidate),
    actions normalized to [-1, 1] of the recorded spec unless --actions raw."""
    eps = generate(12, 40, hidden="none", seed=6)
    path = _write_mcap(eps, tmp_path / "rec.mcap", high=2.0)
    model = get_model(str(ckpt))
    preps = model.prepare(model.load_episodes(path))
    assert len(preps) == 12 and preps[0].states.shape == (41, 2)
    np.testing.assert_allclose(preps[0].actions[:, 0], eps[0].actions[:-1, 0] / 2.0, rtol=1e-5)
    np.testing.assert_allclose(preps[0].features["vbat"][:, 0], eps[0].vbat_v[:-1], rtol=1e-5)
    names, skipped = model.candidate_effects(preps)
    assert "vbat" in names and "action_lag2" in skipped
    raw = get_model(str(ckpt), normalized_actions=False)
    np.testing.assert_allclose(raw.prepare(raw.load_episodes(path))[0].actions[:, 0], eps[0].actions[:-1, 0],
                               rtol=1e-5)
