"""Loading logs through a column map: formats, derived velocity, clear errors."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from hilstack.calibration.data import (
    DataError,
    load_episodes,
    parse_column_map,
    segment_episodes,
    sg_velocity,
    sg_velocity_kernel,
)
from hilstack.calibration.synthetic import SynthConfig, generate, write_csv


def _frame(n=200, period_s=0.01):
    t = np.arange(n) * period_s
    return pd.DataFrame({"time": t, "volts": np.sin(t), "position": np.cos(t)})


def test_column_map_string_and_yaml(tmp_path):
    assert parse_column_map("t=time, u=volts,x=position,vbat=bat") == {
        "t": "time", "u": "volts", "x": "position", "vbat": "bat"}
    y = tmp_path / "map.yaml"
    y.write_text("t: time\nu: volts\nx: position\n")
    assert parse_column_map(y)["u"] == "volts"
    with pytest.raises(DataError, match="unknown column map key"):
        parse_column_map("t=time,u=volts,x=position,q=foo")
    with pytest.raises(DataError, match="required"):
        parse_column_map("t=time,u=volts")


def test_csv_parquet_dir_and_episode_column(tmp_path):
    eps = generate(SynthConfig(n_episodes=3, duration_s=1.0, seed=0, measure_velocity=True))
    csv = write_csv(eps, tmp_path / "log.csv")
    loaded = load_episodes(csv, "t=time,u=volts,x=position,v=velocity")
    assert len(loaded) == 3
    assert np.allclose(loaded[1].x, eps[1].x)
    assert loaded[0].v_meas is not None and loaded[0].period_s == pytest.approx(0.01)
    d = tmp_path / "dir"
    d.mkdir()
    _frame().to_parquet(d / "a.parquet")
    _frame().to_csv(d / "b.csv", index=False)
    assert len(load_episodes(d, "t=time,u=volts,x=position")) == 2


def test_missing_column_names_column_and_file(tmp_path):
    p = tmp_path / "log.csv"
    _frame().to_csv(p, index=False)
    with pytest.raises(DataError) as e:
        load_episodes(p, "t=time,u=voltage,x=position")
    assert "'voltage'" in str(e.value) and str(p) in str(e.value)


def test_mcap_recording_loads_as_episodes(tmp_path):
    """A rig recording (spec + RobotState per period, episode counter) loads through
    hilstack.learning.recordings: one Recording per recorded episode, commands in robot units, the
    action of state k+1 held from t_k to t_{k+1}, channel names from the recorded spec."""
    from hilstack.calibration.synthetic_velociroach import RoachSynthConfig, write_mcap
    from hilstack.calibration.synthetic_velociroach import generate as roach_generate

    src = roach_generate(RoachSynthConfig(n_episodes=2, duration_s=1.0, seed=5))
    path = write_mcap(src, tmp_path / "rec.mcap")
    eps = load_episodes(path)
    assert len(eps) == len(src)
    for got, want in zip(eps, src, strict=True):
        assert got.state_names == want.state_names and got.action_names == ("leg_vel_l", "leg_vel_r")
        np.testing.assert_allclose(got.states, want.states, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(got.actions[:-1], want.actions[:-1], rtol=1e-6)
        assert np.max(np.abs(got.actions)) > 1.5  # rev/s, not normalized to [-1, 1]
        np.testing.assert_allclose(np.diff(got.t_s), 0.1, atol=1e-6)
        np.testing.assert_allclose(got.x, want.states[:, 0], rtol=1e-6)  # default x: the 'x' channel
        np.testing.assert_allclose(got.u, got.actions[:, 0])  # default u: the first action channel
        assert got.vbat_v is not None  # the recording has a 'vbat' state channel
    picked = load_episodes(path, "u=leg_vel_r,x=y")
    np.testing.assert_allclose(picked[0].u, eps[0].actions[:, 1])
    np.testing.assert_allclose(picked[0].x, eps[0].states[:, 1])
    with pytest.raises(DataError, match="'nope'.*not in the recording"):
        load_episodes(path, "x=nope")


def test_mcap_without_states_is_a_data_error(tmp_path):
    from hilstack.bus.recording import McapLog

    p = tmp_path / "empty.mcap"
    with McapLog(p):
        pass
    with pytest.raises(DataError, match="no robot state messages"):  # was "robots []; say which one"
        load_episodes(p)


def test_sg_velocity_kernel_matches_derivative():
    """The SG derivative of position equals the known zero-phase kernel applied to velocity."""
    eps = generate(SynthConfig(n_episodes=1, duration_s=3.0, x_noise_m=0.0, measure_velocity=True,
                               v_noise_mps=0.0, seed=3))
    e = eps[0]
    for w in (7, 11):
        vh = sg_velocity(e.x, e.period_s, w)
        vl = np.convolve(e.v_meas, sg_velocity_kernel(w), mode="same")
        err = np.std((vh - vl)[w:-w])
        assert err < 0.05 * np.std(vh - e.v_meas) + 1e-3


def test_segmenting_long_recordings():
    """Segments tile the recording: every scored row once, context margins overlap the neighbours."""
    eps = generate(SynthConfig(n_episodes=1, duration_s=10.0, seed=0))
    margin = 5
    segs, plan = segment_episodes(eps, min_episodes=10, horizon_steps=50, margin=margin)
    assert plan.segmented and len(segs) == 10 and plan.n_test == 2
    scored = np.concatenate([s.x[margin:-margin] for s in segs])
    np.testing.assert_array_equal(scored, eps[0].x[margin:-margin])
    assert [s.meta["locked_test"] for s in segs] == [False] * 8 + [True] * 2
