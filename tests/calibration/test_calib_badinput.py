"""Bad or awkward input: a one-line error or a warning, never a traceback (issue 9, items 2 and 5)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from hilstack.calibration import run_calibration
from hilstack.calibration.data import DataError, harmonize_rates, load_episodes, parse_column_map, resample
from hilstack.calibration.selection import SelectionConfig
from hilstack.calibration.synthetic import SynthConfig, generate, write_csv
from hilstack.tools.cli import app

#: Cheap statistics: these tests check that the pipeline runs and says the right thing.
CHEAP = SelectionConfig(n_boot=8, max_rounds=1)
runner = CliRunner()


def _run(eps_or_path, tmp_path, **kw):
    return run_calibration(eps_or_path, out_dir=tmp_path / "out", progress=False, plots=False, config=CHEAP, **kw)


def _cli(args):
    return runner.invoke(app, ["calibrate", *args, "--quiet"])


def test_non_numeric_cell_names_file_row_and_column(tmp_path):
    eps = generate(SynthConfig(n_episodes=2, duration_s=1.0, seed=0))
    p = write_csv(eps, tmp_path / "log.csv")
    df = pd.read_csv(p)
    df["volts"] = df["volts"].astype(object)
    df.loc[33, "volts"] = "1,5"
    df.to_csv(p, index=False)
    with pytest.raises(DataError) as e:
        load_episodes(p, "t=time,u=volts,x=position")
    msg = str(e.value)
    assert str(p) in msg and "'volts'" in msg and "data row 33" in msg and "'1,5'" in msg
    res = _cli(["--data", str(p), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "non-numeric" in res.output and "Traceback" not in res.output


def test_map_naming_a_column_twice_is_refused():
    with pytest.raises(DataError, match="'time' twice"):
        parse_column_map("t=time,u=time,x=position")
    with pytest.raises(DataError, match="key 'x' twice"):
        parse_column_map("t=time,u=volts,x=position,x=pos2")


def test_nan_rows_are_dropped_and_the_episode_split(tmp_path):
    eps = generate(SynthConfig(n_episodes=1, duration_s=2.0, seed=0))
    p = write_csv(eps, tmp_path / "log.csv")
    df = pd.read_csv(p)
    df.loc[[57, 58, 150], "position"] = np.nan
    df.to_csv(p, index=False)
    warned: list[str] = []
    got = load_episodes(p, "t=time,u=volts,x=position", warn=warned.append)
    assert [e.n for e in got] == [57, 150 - 59, 200 - 151]  # every clean row kept
    assert len(warned) == 1 and "3 row(s)" in warned[0] and "data row 57" in warned[0] and "'position'" in warned[0]
    np.testing.assert_array_equal(got[1].x, eps[0].x[59:150])


def test_too_short_episode_is_skipped_with_a_warning(tmp_path):
    eps = generate(SynthConfig(n_episodes=2, duration_s=1.0, seed=0))
    eps[1] = eps[1].slice(0, 12, "tiny")
    p = write_csv(eps, tmp_path / "log.csv")
    warned: list[str] = []
    assert len(load_episodes(p, "t=time,u=volts,x=position", warn=warned.append)) == 1
    assert "only 12 samples" in warned[0]


def test_single_long_recording_uses_blocked_folds_with_a_locked_final_block(tmp_path):
    """One recording: contiguous segments, the final block locked for test, contiguous folds."""
    eps = generate(SynthConfig(n_episodes=1, duration_s=40.0, seed=2, effects={"coulomb_friction": {}}))
    r = _run(eps, tmp_path)
    assert r["data"]["segmented"] is True and "final" in r["data"]["segmentation_note"]
    segs = [int(n.split("[seg")[1].rstrip("]")) for n in r["folds"]["test_episodes"]]
    n_units = r["data"]["n_episodes"]
    assert segs == list(range(n_units - len(segs), n_units))  # the last segments in time
    for fold in r["folds"]["fold_episodes"]:
        idx = [int(n.split("[seg")[1].rstrip("]")) for n in fold]
        assert idx == list(range(idx[0], idx[0] + len(idx)))  # each fold is one contiguous block
    assert r["verdict"] == "found" and r["effects"][0]["name"] == "coulomb_friction"


def test_short_recording_shortens_the_horizon_and_still_runs(tmp_path):
    eps = generate(SynthConfig(n_episodes=1, duration_s=8.0, seed=3, effects={"coulomb_friction": {}}))
    r = _run(eps, tmp_path)
    assert r["folds"]["horizon_steps"] < 100  # 1 s at 100 Hz did not fit 20 segments of 8 s
    assert any("horizon shortened" in w for w in r["warnings"])
    assert r["data"]["n_episodes"] >= 8


def test_too_short_recording_is_a_clear_error(tmp_path):
    eps = generate(SynthConfig(n_episodes=1, duration_s=1.5, seed=3))
    with pytest.raises(DataError, match="data too short to calibrate.*need at least"):
        _run(eps, tmp_path)


def _at_rest(e, name):
    rng = np.random.default_rng(0)
    return replace(e, name=name, u=np.zeros(e.n), x=0.3 + 2e-4 * rng.standard_normal(e.n))


def test_episodes_without_motion_are_skipped_with_a_warning(tmp_path):
    eps = generate(SynthConfig(n_episodes=12, duration_s=3.0, seed=4))
    eps[3] = _at_rest(eps[3], "rest3")
    eps[7] = _at_rest(eps[7], "rest7")
    r = _run(eps, tmp_path)
    skipped = [w for w in r["warnings"] if "barely moves" in w]
    assert len(skipped) == 2 and "rest3" in skipped[0] and "rest7" in skipped[1]
    assert r["verdict"] == "none"


def test_only_motionless_episodes_is_a_clear_error(tmp_path):
    eps = [_at_rest(e, f"rest{i}") for i, e in enumerate(generate(SynthConfig(n_episodes=3, duration_s=2.0)))]
    with pytest.raises(DataError, match="no episode with motion"):
        _run(eps, tmp_path)


def test_resample_averages_the_zoh_command():
    e = generate(SynthConfig(n_episodes=1, duration_s=2.0, period_s=0.01, seed=5))[0]
    r = resample(e, 0.02)
    assert r.n == 100 and np.allclose(np.diff(r.t_s), 0.02)
    np.testing.assert_allclose(r.u[:-1], 0.5 * (e.u[0:-2:2] + e.u[1:-1:2]))
    np.testing.assert_allclose(r.x, e.x[::2])


def test_mixed_sample_rates_are_resampled_with_a_warning(tmp_path):
    """20 and 40 Hz episodes: resampled to 20 Hz with a warning naming both rates; the model fit on
    the mixture predicts as well as one fit on 20 Hz data alone (no silent wrong period)."""
    slow = generate(SynthConfig(n_episodes=8, duration_s=6.0, period_s=0.05, substeps=50, seed=6))
    fast = generate(SynthConfig(n_episodes=8, duration_s=6.0, period_s=0.025, substeps=25, seed=7))
    warned: list[str] = []
    mixed = harmonize_rates(slow + fast, warn=warned.append)
    assert len(warned) == 1 and "20 Hz" in warned[0].replace("20.0", "20") and "40" in warned[0]
    assert all(abs(e.period_s - 0.05) < 1e-9 for e in mixed)
    r = _run(slow + fast, tmp_path)
    assert any("different rates" in w for w in r["warnings"])
    ref = _run(slow + generate(SynthConfig(n_episodes=8, duration_s=6.0, period_s=0.05, substeps=50, seed=7)),
               tmp_path / "ref")
    assert r["before"]["multi_step_nrmse"]["mean"] < 1.5 * ref["before"]["multi_step_nrmse"]["mean"]
    assert r["final_params"]["coef"]["a"] == pytest.approx(ref["final_params"]["coef"]["a"], rel=0.05)


def test_quantised_finite_difference_velocity_is_not_used_as_the_state():
    """Velocity logged as the difference of a 1 mm encoder (0.1 m/s steps) is replaced by the
    smoothed derivative of position; a genuinely measured velocity is kept."""
    from hilstack.calibration import axis

    quant = generate(SynthConfig(n_episodes=3, seed=1, x_quant=1e-3, velocity_from_differences=True))
    good = generate(SynthConfig(n_episodes=3, seed=1, measure_velocity=True))
    assert not axis.logged_velocity_usable(quant, 0.01, 7)
    assert axis.logged_velocity_usable(good, 0.01, 7)
    pq, pg = axis.prepare(quant)[0], axis.prepare(good)[0]
    assert pq.kernel is not None and np.array_equal(pq.v_obs, pq.v_from_x)
    assert pg.kernel is None and np.array_equal(pg.v_obs, good[0].v_meas)


# ------------------------------------------------------------------ issue 22 item 15: bad files, memory


def _ok_csv(tmp_path, name="ok.csv", duration_s=30.0):
    return write_csv(generate(SynthConfig(n_episodes=1, duration_s=duration_s, seed=0)), tmp_path / name)


def _bad_file(tmp_path, kind: str):
    rng = np.random.default_rng(0)
    if kind == "empty.csv" or kind == "empty.parquet":
        p = tmp_path / kind
        p.write_bytes(b"")
    elif kind == "header_only.csv":
        p = tmp_path / kind
        p.write_text("time,volts,position\n")
    elif kind in ("binary.csv", "random.parquet", "random.mcap"):
        p = tmp_path / kind
        p.write_bytes(rng.integers(0, 256, 5000, dtype=np.uint8).tobytes())
    elif kind == "garbage_body.mcap":
        p = tmp_path / kind
        p.write_bytes(b"\x89MCAP0\r\n" + rng.integers(0, 256, 3000, dtype=np.uint8).tobytes())
    elif kind in ("constant.csv", "constant_command.csv"):
        p = _ok_csv(tmp_path, kind, 3.0)
        df = pd.read_csv(p)
        df["volts"] = 1.0
        if kind == "constant.csv":
            df["position"] = 0.5
        df.to_csv(p, index=False)
    return p


BAD_FILES = {
    "empty.csv": "is empty (0 bytes)",
    "empty.parquet": "is empty (0 bytes)",
    "header_only.csv": "no data rows",
    "binary.csv": "is not a text CSV file",
    "random.parquet": "is not a readable Parquet file",
    "random.mcap": "is not an MCAP file",
    "garbage_body.mcap": "no robot state messages",
    "constant.csv": "no usable episode",
    "constant_command.csv": "command column 'volts' is constant",
}


@pytest.mark.parametrize("kind", list(BAD_FILES))
def test_unreadable_or_degenerate_file_is_a_one_line_error(tmp_path, kind):
    """Issue 22 item 15: each of these was a traceback (pandas, pyarrow, the report's formatting) or
    'recording has robots []; say which one'; now one line naming the file and what is wrong, exit 2."""
    p = _bad_file(tmp_path, kind)
    res = _cli(["--data", str(p), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and "robots []" not in res.output
    err = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and BAD_FILES[kind] in err[0] and p.name in err[0], res.output


def test_huge_values_are_dropped_like_nan_with_a_warning(tmp_path):
    """1e300 in a cell overflowed squares downstream (a TypeError in the report); such rows are now
    dropped like NaN rows (|value| > MAX_ABS_VALUE), the recording split there, and the run completes."""
    from hilstack.calibration.data import MAX_ABS_VALUE

    p = _ok_csv(tmp_path, duration_s=10.0)
    df = pd.read_csv(p)
    df.loc[400:402, "volts"] = 1e300
    df.to_csv(p, index=False)
    warned: list[str] = []
    got = load_episodes(p, "t=time,u=volts,x=position", warn=warned.append)
    assert [e.n for e in got] == [400, 1000 - 403]
    assert len(warned) == 1 and "3 row(s)" in warned[0] and f"{MAX_ABS_VALUE:g}" in warned[0] and "'volts'" in warned[0]
    res = _cli(["--data", str(p), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0 and "Traceback" not in res.output and "dropped" in res.output


def test_out_at_an_existing_file_is_refused_and_the_file_kept(tmp_path):
    p = _ok_csv(tmp_path, duration_s=3.0)
    keep = tmp_path / "notes.txt"
    keep.write_text("lab notes")
    res = _cli(["--data", str(p), "--out", str(keep)])
    assert res.exit_code == 2 and "Traceback" not in res.output and "existing file" in res.output
    assert keep.read_text() == "lab notes"


def test_time_gap_splits_the_recording_by_the_stated_rule(tmp_path):
    """A step longer than GAP_PERIODS median periods starts a new episode; nothing is resampled across it,
    so the loaded samples never exceed the rows in the file (memory bounded by the data size)."""
    from hilstack.calibration.data import GAP_PERIODS

    p = _ok_csv(tmp_path, duration_s=30.0)
    df = pd.read_csv(p)
    df.loc[1500:, "time"] += 1e4  # 1e6 samples if resampled across at 100 Hz
    df.loc[2200:, "time"] += (GAP_PERIODS - 2) * 0.01  # below the rule: kept (and resampled)
    df.to_csv(p, index=False)
    warned: list[str] = []
    got = load_episodes(p, "t=time,u=volts,x=position", warn=warned.append)
    assert len(got) == 2 and got[0].n == 1500
    assert sum(e.n for e in got) <= len(df) + GAP_PERIODS
    assert len(warned) == 1 and "1 time gap(s)" in warned[0] and f"{GAP_PERIODS:g} median periods" in warned[0]


def test_clock_jump_of_1e6_s_keeps_memory_bounded(tmp_path):
    """Issue 22 item 15: `hil calibrate` on a 3000-row CSV with one 1e6 s jump grew to 5.2 GB. Run the real
    CLI in a child process under a 3 GB address-space limit: it must finish (the gap splits the recording)."""
    import os
    import resource
    import subprocess
    import sys

    p = _ok_csv(tmp_path, duration_s=30.0)
    df = pd.read_csv(p)
    df.loc[1500:, "time"] += 1e6
    df.to_csv(p, index=False)

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))

    r = subprocess.run([sys.executable, "-m", "hilstack.tools.cli", "calibrate", "--data", str(p), "--out",
                        str(tmp_path / "o"), "--quiet", "--json"], capture_output=True, text=True,
                       preexec_fn=limit, timeout=600, env=os.environ.copy())
    assert r.returncode == 0, r.stderr[-2000:]
    assert "time gap(s)" in r.stderr and "Traceback" not in r.stderr
