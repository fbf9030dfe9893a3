"""Episodes, transition datasets and tabular loading."""

import numpy as np
import pandas as pd
import pytest

from hilstack.learning.datasets import (
    Episode,
    TransitionDataset,
    Transitions,
    episodes_from_table,
    load_episodes,
)
from tests.helpers import spec_dict


def make_episode(T, offset, name=""):
    s = offset + np.arange((T + 1) * 2, dtype=np.float32).reshape(T + 1, 2)
    a = np.full((T, 1), offset, dtype=np.float32)
    return Episode(s, a, times=np.arange(T + 1) * 0.1, name=name)


def test_episode_validates_shapes():
    with pytest.raises(ValueError):
        Episode(np.zeros((5, 2)), np.zeros((5, 1)))
    with pytest.raises(ValueError):
        Episode(np.zeros((5, 2)), np.zeros((4, 1)), times=np.zeros(4))
    assert len(make_episode(4, 0.0)) == 4


def test_the_transition_record_pairs_each_action_with_its_state_and_the_next():
    a = make_episode(3, 0.0, "a")
    a.meta.update(state_names=["p", "v"], action_names=["u"])
    tr = Transitions.from_episodes([a, make_episode(2, 100.0, "b")])
    assert len(tr) == 5 and tr.state_names == ("p", "v") and tr.action_names == ("u",)
    np.testing.assert_array_equal(tr.states[2], a.states[2])
    np.testing.assert_array_equal(tr.next_states[2], a.states[3])  # a's last transition, not b's first state
    np.testing.assert_array_equal(tr.states[3], [100.0, 101.0])
    np.testing.assert_array_equal(tr.actions[:, 0], [0, 0, 0, 100, 100])
    np.testing.assert_allclose(tr.deltas, np.full((5, 2), 2.0))
    sub = tr.subset(np.array([1, 3]))
    np.testing.assert_array_equal(sub.states, tr.states[[1, 3]])
    np.testing.assert_array_equal(sub.next_states, tr.next_states[[1, 3]])
    assert sub.state_names == ("p", "v") and len(sub) == 2
    assert a.transitions().arrays()[0].shape == (3, 2)
    with pytest.raises(ValueError, match=r"next_states \(4, 2\) must be"):
        Transitions(np.zeros((5, 2)), np.zeros((5, 1)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="action_names has 2 entries, the data 1 channels"):
        Transitions(np.zeros((5, 2)), np.zeros((5, 1)), np.zeros((5, 2)), action_names=("u", "w"))


def test_transitions_and_deltas():
    ds = TransitionDataset([make_episode(3, 0.0, "a"), make_episode(2, 100.0, "b")])
    assert len(ds) == 5
    np.testing.assert_array_equal(ds.episode_index, [0, 0, 0, 1, 1])
    np.testing.assert_allclose(ds.deltas, np.full((5, 2), 2.0))
    np.testing.assert_allclose(ds.states[3], [100.0, 101.0])
    np.testing.assert_allclose(ds.actions[:, 0], [0, 0, 0, 100, 100])


def test_stats_are_from_data_and_safe_for_constant_channels():
    ds = TransitionDataset([make_episode(3, 0.0), make_episode(3, 10.0)])
    st = ds.stats()
    x = np.concatenate([ds.states, ds.actions], 1)
    np.testing.assert_allclose(st.input_mean, x.mean(0), rtol=1e-6)
    np.testing.assert_allclose(st.input_std, x.std(0), rtol=1e-6)
    np.testing.assert_allclose(st.delta_std, [1.0, 1.0])  # constant deltas: std replaced by 1
    np.testing.assert_allclose(st.delta_mean, [2.0, 2.0])


def test_split_is_by_whole_episode_and_reproducible():
    eps = [make_episode(5, 10.0 * i, f"e{i}") for i in range(10)]
    ds = TransitionDataset(eps)
    tr, va = ds.split(0.3, seed=1)
    names_tr = {e.name for e in tr.episodes}
    names_va = {e.name for e in va.episodes}
    assert len(names_va) == 3 and not names_tr & names_va and len(names_tr | names_va) == 10
    assert len(tr) + len(va) == len(ds)
    tr2, va2 = ds.split(0.3, seed=1)
    assert [e.name for e in va2.episodes] == [e.name for e in va.episodes]
    with pytest.raises(ValueError):
        TransitionDataset(eps[:1]).split()


def test_aggregation():
    a = TransitionDataset([make_episode(3, 0.0)], state_names=["p", "v"], action_names=["u"])
    b = a.extend([make_episode(2, 5.0)])
    assert len(b) == 5 and len(a) == 3 and b.state_names == ["p", "v"]
    c = a + b
    assert len(c) == 8 and len(c.episodes) == 3
    assert len(TransitionDataset.concatenate([a, b, c])) == 16
    with pytest.raises(ValueError):
        TransitionDataset([make_episode(3, 0.0)], state_names=["p"])


def _table():
    rows = []
    for ep in ("run1", "run2"):
        for t in range(4):
            rows.append({"run": ep, "t": 0.1 * t, "px": t, "pv": 2 * t, "u": t + 0.5, "junk": 9})
    return pd.DataFrame(rows)


def test_episodes_from_table_with_column_map():
    eps = episodes_from_table(_table(), state=["px", "pv"], action=["u"], episode="run", time="t")
    assert [e.name for e in eps] == ["run1", "run2"]
    assert eps[0].states.shape == (4, 2) and eps[0].actions.shape == (3, 1)
    np.testing.assert_allclose(eps[0].actions[:, 0], [0.5, 1.5, 2.5])  # last row's action unused
    np.testing.assert_allclose(eps[0].times, [0, 0.1, 0.2, 0.3])
    ds = TransitionDataset(eps)
    assert ds.state_names == ["px", "pv"] and ds.action_names == ["u"]
    with pytest.raises(KeyError, match="nope"):
        episodes_from_table(_table(), state=["nope"], action=["u"])


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_load_episodes_from_files(tmp_path, suffix):
    path = tmp_path / f"log{suffix}"
    t = _table()
    t.to_csv(path, index=False) if suffix == ".csv" else t.to_parquet(path)
    eps = load_episodes(path, state=["px", "pv"], action=["u"], episode="run")
    assert len(eps) == 2 and eps[1].states.shape == (4, 2)


def test_load_episodes_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown"):
        load_episodes(tmp_path / "x.txt", state=["a"], action=["b"])
    (tmp_path / "x.csv").write_text("a,b\n1,2\n3,4\n")
    with pytest.raises(TypeError):
        load_episodes(tmp_path / "x.csv")


def test_mcap_recordings_load_through_the_same_entry_point(tmp_path):
    from hilstack.bus import keys
    from hilstack.bus.recording import McapLog
    from hilstack.bus.schemas import RobotState, SpecMsg

    spec = spec_dict("roach", ["x"], ["u"])
    with McapLog(tmp_path / "session.mcap") as log:
        log.write(keys.spec("r", "roach"), SpecMsg(robot="roach", spec=spec))
        for i in range(5):
            log.write(keys.state("r", "roach"),
                      RobotState(robot="roach", t_s=0.1 * i, state=[float(i)], action=[0.5], seq=i + 1))
    (ep,) = load_episodes(tmp_path / "session.mcap", robot="roach")
    np.testing.assert_allclose(ep.states[:, 0], np.arange(5))
    np.testing.assert_allclose(ep.actions[:, 0], 0.5)


def test_action_alignment_actions_t_leads_from_states_t_to_states_t_plus_1():
    """The one alignment of learning's Episode (and of a calibration recording's transitions):
    ``actions[t]`` is applied at ``states[t]`` and leads to ``states[t+1]``. On s' = s + a the
    deltas equal the actions exactly; any off-by-one pairing breaks that."""
    from hilstack.calibration.data import Recording
    from hilstack.learning.datasets import Episode as Ep
    from hilstack.learning.datasets import TransitionDataset as TD

    rng = np.random.default_rng(0)
    a = rng.integers(-5, 6, size=(12, 2)).astype(np.float32)
    s = np.concatenate([np.zeros((1, 2), np.float32), np.cumsum(a, axis=0)])  # s[t+1] = s[t] + a[t]
    ds = TD([Ep(s, a, name="e")])
    np.testing.assert_array_equal(ds.deltas, ds.actions)
    np.testing.assert_array_equal(ds.states, s[:-1])
    # a recording holds one action per sample, actions[k] from t_k to t_{k+1}, the last row repeated
    rec = Recording(name="r", t_s=np.arange(13) * 0.1, u=np.zeros(13), x=np.zeros(13), states=s,
                    actions=np.concatenate([a, a[-1:]]), state_names=("p", "q"), action_names=("u", "v"))
    tr = rec.transitions()
    np.testing.assert_array_equal(tr.actions, a)
    np.testing.assert_array_equal(TD([tr]).deltas, a)
    np.testing.assert_array_equal(rec.transitions(("q",), ("v",)).actions[:, 0], a[:, 1])
