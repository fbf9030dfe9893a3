"""EnsembleDynamics: batching, normalization, training, validation, checkpoints."""

import numpy as np
import pytest
import torch

from hilstack.learning.datasets import Episode, TransitionDataset
from hilstack.learning.dynamics import EnsembleDynamics, cpu_bf16_support, h_step_error, h_step_windows

A_TRUE = np.array([[0.95, 0.1], [-0.1, 0.9]], dtype=np.float32)
B_TRUE = np.array([[0.0], [0.5]], dtype=np.float32)


def linear_episodes(n, T=40, seed=0, scale=1.0):
    """x' = A x + B u + c, with states far from zero mean/unit scale (normalization matters)."""
    rng = np.random.default_rng(seed)
    eps = []
    for i in range(n):
        s = np.zeros((T + 1, 2), np.float32)
        s[0] = rng.normal(size=2)
        a = rng.uniform(-1, 1, (T, 1)).astype(np.float32)
        for t in range(T):
            s[t + 1] = A_TRUE @ s[t] + B_TRUE @ a[t] + 0.02
        eps.append(Episode(scale * s + np.float32(5.0), a, name=f"ep{i}"))
    return eps


@pytest.fixture(scope="module")
def data():
    ds = TransitionDataset(linear_episodes(24), state_names=["p", "v"], action_names=["u"],
                           state_units=["m", "m/s"], action_units=["1"])
    return ds.split(0.25, seed=0)


def test_ensemble_is_one_batched_computation_equal_to_per_member_mlps():
    m = EnsembleDynamics(3, 2, ensemble=4, hidden=(8, 6), seed=1)
    x = torch.randn(4, 5, 5)
    out = m.forward_normalized(x)
    for e in range(4):
        h = x[e]
        for i, (w, b) in enumerate(zip(m.weights, m.biases, strict=True)):
            h = h @ w[e] + b[e]
            if i < 2:
                h = torch.relu(h)
        assert torch.allclose(out[e], h, atol=1e-6)
    assert m.weights[1].shape == (4, 8, 6)
    # members start from different weights
    assert not torch.allclose(m.weights[0][0], m.weights[0][1])


def test_predict_shapes_and_fast_path_matches_differentiable_path():
    m = EnsembleDynamics(3, 2, ensemble=3, hidden=(16, 16), seed=2)
    with torch.no_grad():  # non-trivial normalization so folding it into the weights is exercised
        m.input_mean.copy_(torch.tensor([1.0, -2.0, 0.5, 0.1, 0.2]))
        m.input_std.copy_(torch.tensor([2.0, 0.5, 1.0, 3.0, 0.2]))
        m.delta_mean.copy_(torch.tensor([0.1, 0.0, -0.3]))
        m.delta_std.copy_(torch.tensor([0.5, 2.0, 1.0]))
        m._fast = None
    for B in (5, 256):  # 256 exercises the chunked batch layout
        s, a = torch.randn(B, 3), torch.randn(B, 2)
        ref = m.predict(s, a).detach()  # grad enabled: differentiable path
        assert ref.shape == (3, B, 3)
        with torch.inference_mode():
            fast = m.predict(s, a)
            fast3 = m.predict(s.expand(3, B, 3), a)
        assert torch.allclose(fast, ref, atol=1e-5)
        assert torch.allclose(fast3, ref, atol=1e-5)
    with pytest.raises(ValueError):
        m.predict(torch.randn(2, 4, 3), torch.randn(4, 2))


def test_bf16_inference_is_close_when_available():
    m = EnsembleDynamics(4, 2, ensemble=2, hidden=(32, 32), seed=3)
    s, a = torch.randn(10, 4), torch.randn(10, 2)
    with torch.inference_mode():
        ref = m.predict(s, a)
        dt = m.set_inference_dtype("bf16")
        out = m.predict(s, a)
    assert out.dtype == torch.float32
    assert dt == (torch.bfloat16 if cpu_bf16_support() else torch.float32)
    assert torch.allclose(out, ref, atol=0.05)


def test_auto_precision_takes_bf16_only_where_it_measured_faster(monkeypatch):
    """``auto`` times the model in both precisions on CPUs with native bf16 and takes bf16 only
    at >= AUTO_BF16_MIN_SPEEDUP; without native bf16 it is fp32 and measures nothing."""
    import hilstack.learning.dynamics as dyn

    m = EnsembleDynamics(4, 2, ensemble=2, hidden=(32, 32), seed=3)
    for support, speedup, want in (("avx512", 2.0, torch.bfloat16), ("avx512", 1.1, torch.float32),
                                   ("amx", 1.3, torch.bfloat16), ("amx", 0.5, torch.float32)):
        monkeypatch.setattr(dyn, "cpu_bf16_support", lambda s=support: s)
        monkeypatch.setattr(m, "measure_dtypes", lambda x=speedup: {"speedup": x})
        assert m.set_inference_dtype("auto") == want, (support, speedup)
    monkeypatch.setattr(dyn, "cpu_bf16_support", lambda: None)
    monkeypatch.setattr(m, "measure_dtypes", lambda: pytest.fail("measured without native bf16"))
    assert m.set_inference_dtype("auto") == torch.float32 and m.set_inference_dtype("bf16") == torch.float32


def test_measure_dtypes_times_both_and_keeps_the_precision_in_use():
    m = EnsembleDynamics(4, 2, ensemble=2, hidden=(32, 32), seed=3)
    s, a = torch.randn(10, 4), torch.randn(10, 2)
    with torch.inference_mode():
        before = m.predict(s, a)
    got = m.measure_dtypes(batch=64, reps=2)
    assert got is m.dtype_measurement and got["batch"] == 64
    assert got["fp32_ms"] > 0 and got["bf16_ms"] > 0 and got["speedup"] == pytest.approx(got["fp32_ms"] / got["bf16_ms"])
    assert m.inference_dtype == torch.float32
    with torch.inference_mode():
        assert torch.equal(m.predict(s, a), before)  # still the fp32 weights, not a bf16 copy


def test_cpu_flag_detection(tmp_path):
    f = tmp_path / "cpuinfo"
    f.write_text("processor: 0\nflags\t\t: fpu sse avx512f avx512_bf16\n")
    assert cpu_bf16_support(f) == "avx512"
    f.write_text("flags: fpu amx_bf16 amx_tile avx512_bf16\n")
    assert cpu_bf16_support(f) == "amx"
    f.write_text("flags: fpu sse2\n")
    assert cpu_bf16_support(f) is None
    assert cpu_bf16_support(tmp_path / "missing") is None


def test_fit_learns_linear_system_and_tracks_validation(data):
    train, val = data
    m = EnsembleDynamics(2, 1, ensemble=2, hidden=(64, 64), seed=0)
    hist = m.fit(train, epochs=25, batch_size=64, progress=False, val=val, horizon=5)
    assert len(hist) == 25 and [h["epoch"] for h in hist] == list(range(25))
    assert hist[-1]["train_loss"] < 0.2 * hist[0]["train_loss"]
    assert hist[-1]["val_h"] < 0.2 * hist[0]["val_h"]
    assert hist[-1]["val_1step"] < hist[0]["val_1step"]
    assert {"val_1step", "val_h", "val_h_raw", "horizon", "time_s"} <= set(hist[-1])
    # normalization statistics come from the data
    x = np.concatenate([train.states, train.actions], 1)
    np.testing.assert_allclose(m.input_mean.numpy(), x.mean(0), rtol=1e-5)
    assert m.state_names == ["p", "v"] and m.state_units == ["m", "m/s"]


def test_h_step_error_is_eqn_2_2():
    eps = linear_episodes(2, T=8)
    m = EnsembleDynamics(2, 1, ensemble=2, hidden=(4,), seed=5)
    s, a, y = h_step_windows(eps, 3, max_starts=None)
    assert s.shape == (2 * 6, 2) and a.shape == (12, 3, 1) and y.shape == (12, 3, 2)
    np.testing.assert_allclose(y[1, 2], eps[0].states[4])
    norm, raw = h_step_error(m, s, a, y)
    # hand computation: roll each member out open loop, replaying the logged actions
    with torch.inference_mode():
        cur = torch.from_numpy(s)
        errs = []
        for h in range(3):
            cur = m.predict(cur, torch.from_numpy(a[:, h]))
            errs.append(0.5 * ((cur - torch.from_numpy(y[:, h])) ** 2).sum(-1))  # [E, P]
        hand = torch.stack(errs).mean().item()
    assert raw == pytest.approx(hand, rel=1e-5)
    assert norm == pytest.approx(raw, rel=1e-5)  # unfitted model: state std is 1


def test_warm_start_continues_and_refit_preserves_function(data):
    train, val = data
    m = EnsembleDynamics(2, 1, ensemble=2, hidden=(32, 32), seed=0)
    m.fit(train, epochs=3, batch_size=64, progress=False)
    s, a = torch.randn(16, 2) + 5, torch.randn(16, 1)
    with torch.inference_mode():
        before = m.predict(s, a).clone()
    # new data with other statistics: refit moves the stats but not the function
    more = TransitionDataset(linear_episodes(6, seed=7, scale=3.0))
    agg = train.extend(more.episodes)
    m._set_stats(agg.stats())
    with torch.inference_mode():
        after = m.predict(s, a)
    assert not torch.allclose(m.input_std, torch.from_numpy(train.stats().input_std))
    assert torch.allclose(before, after, atol=1e-4)
    h2 = m.fit(agg, epochs=2, batch_size=64, progress=False)
    assert [h["epoch"] for h in h2] == [3, 4] and len(m.history) == 5


def test_freeze_keeps_first_statistics(data):
    train, _ = data
    m = EnsembleDynamics(2, 1, hidden=(8,), norm_update="freeze", seed=0)
    m.fit(train, epochs=1, progress=False)
    mean0 = m.input_mean.clone()
    m.fit(TransitionDataset(linear_episodes(3, seed=9, scale=4.0)), epochs=1, progress=False)
    assert torch.equal(m.input_mean, mean0)


def test_bootstrap_members_see_different_data(data):
    train, _ = data
    m = EnsembleDynamics(2, 1, ensemble=3, hidden=(8,), seed=0)
    assert m.config["bootstrap"] and not EnsembleDynamics(2, 1).config["bootstrap"]
    m.fit(train, epochs=1, progress=False)
    w = m.weights[0]
    assert not torch.allclose(w[0], w[1])


def test_input_noise_option_trains(data):
    train, _ = data
    m = EnsembleDynamics(2, 1, hidden=(16,), input_noise_std=0.1, seed=0)
    h = m.fit(train, epochs=3, batch_size=64, progress=False)
    assert all(np.isfinite(e["train_loss"]) for e in h)


def test_save_load_roundtrip(tmp_path, data):
    train, val = data
    m = EnsembleDynamics(2, 1, ensemble=2, hidden=(16, 16), input_noise_std=0.01, seed=0)
    m.fit(train, epochs=2, batch_size=64, progress=False, val=val, horizon=3)
    path = tmp_path / "model.pt"
    m.save(path)
    raw = torch.load(path, weights_only=True)
    assert raw["config"]["ensemble"] == 2 and raw["state_names"] == ["p", "v"]
    m2 = EnsembleDynamics.load(path)
    assert m2.history == m.history and m2.config == m.config
    assert m2.action_units == ["1"]
    s, a = torch.randn(9, 2), torch.randn(9, 1)
    with torch.inference_mode():
        assert torch.allclose(m.predict(s, a), m2.predict(s, a))
    m2.fit(train, epochs=1, progress=False)  # a loaded model warm-starts too
    assert m2.history[-1]["epoch"] == 2
    torch.save({"format": "other"}, tmp_path / "bad.pt")
    with pytest.raises(ValueError):
        EnsembleDynamics.load(tmp_path / "bad.pt")


def test_model_plugs_into_planner():
    from hilstack.control.planners import PDDM

    m = EnsembleDynamics(2, 1, ensemble=3, hidden=(16,), seed=0)
    p = PDDM(-1.0, 1.0, horizon=4, samples=32, action_dim=1)
    a = p(m, lambda st, ac: st[..., -1, 0] ** 2, np.zeros(2, np.float32))
    assert a.shape == (1,) and p.last_predicted_states.shape == (3, 5, 2)


@pytest.mark.skipif(cpu_bf16_support() is None, reason="no native bf16 on this CPU: inference stays fp32")
def test_bf16_inference_keeps_the_resolution_of_states_far_from_zero():
    """States like world-frame ball positions (~1 m, moving by mm): bf16 has 8 bits of
    mantissa, so casting the raw state (4-8 mm steps at 1 m) before normalising loses the
    motion; the inference path normalises in fp32 first. The prediction of two states 1 mm
    apart must differ as in fp32."""
    torch.manual_seed(0)
    s = 1.0 + 0.01 * torch.randn(256, 3)
    a = torch.randn(256, 2)
    nxt = s + 0.1 * (s - 1.0) + 0.01 * a[:, :1]
    m = EnsembleDynamics(3, 2, ensemble=2, hidden=(32, 32), seed=3)
    m.fit([Episode(states=torch.cat([s[:1], nxt]).numpy()[:2], actions=a[:1].numpy())] +
          [Episode(states=np.stack([s[i].numpy(), nxt[i].numpy()]), actions=a[i:i + 1].numpy()) for i in range(256)],
          epochs=1, batch_size=64, progress=False)
    probe = s[:64].clone()
    probe2 = probe + torch.tensor([1e-3, 0.0, 0.0])
    with torch.inference_mode():
        ref = m.predict(probe2, a[:64]) - m.predict(probe, a[:64])
        m.set_inference_dtype("bf16")
        out = m.predict(probe2, a[:64]) - m.predict(probe, a[:64])
    err = (out - ref).abs().max().item()
    assert err < 0.2 * ref.abs().max().item() + 1e-4, (err, ref.abs().max().item())


def test_the_bf16_relu_on_the_int16_view_is_exactly_relu():
    """The planner's bf16 ReLU works on the bits (learning/dynamics.py ``_relu_``): every value,
    negatives, ±0, tiny and huge, subnormals and ±inf, must come out as torch's relu gives it."""
    from hilstack.learning.dynamics import _relu_

    bits = torch.arange(-32768, 32768, dtype=torch.int32).to(torch.int16)  # every bf16 bit pattern
    x = bits.view(torch.bfloat16)
    x = x[~torch.isnan(x)]  # a NaN with the sign bit set becomes 0 here (torch keeps it NaN): not a planner value
    want = torch.relu(x.float()).to(torch.bfloat16)
    got = _relu_(x.clone())
    assert torch.equal(got.float(), want.float())  # −0 and +0 compare equal; every other value exactly
    f = torch.randn(1000)
    assert torch.equal(_relu_(f.clone()), torch.relu(f))  # fp32: the plain relu


def test_loss_weights_decide_which_channels_are_learned(tmp_path, data):
    """A channel weighted 0 in the training loss is not learned; the other one is (issue 29's
    tilt weight is this option); the weights survive a checkpoint and bad ones are refused."""
    train, val = data
    errs = {}
    for w in ([1.0, 0.0], [0.0, 1.0]):
        m = EnsembleDynamics(2, 1, hidden=(32, 32), loss_weights=w, seed=0)
        m.fit(train, epochs=60, progress=False)
        with torch.inference_mode():
            pred = m.predict(torch.from_numpy(val.states), torch.from_numpy(val.actions))[0].numpy()
        errs[tuple(w)] = np.sqrt(((pred - val.states - val.deltas) ** 2).mean(0)) / val.deltas.std(0)
    # the learned channel's error is a small fraction of its delta's spread; the ignored one's is not
    assert errs[(1.0, 0.0)][0] < 0.1 < errs[(1.0, 0.0)][1]
    assert errs[(0.0, 1.0)][1] < 0.1 < errs[(0.0, 1.0)][0]
    m.save(tmp_path / "w.pt")
    assert EnsembleDynamics.load(tmp_path / "w.pt").config["loss_weights"] == [0.0, 1.0]
    for bad in ([1.0], [1.0, -1.0], [0.0, 0.0], [1.0, float("nan")]):
        with pytest.raises(ValueError, match="loss_weights"):
            EnsembleDynamics(2, 1, loss_weights=bad)
def test_noise_to_signal_is_in_proportion_to_each_channels_std_on_states_and_targets_and_only_in_training():
    """The reference code's supervised-learning noise (pddm ``noiseToSignal``), scaled by the
    spread: each state input and delta target gets noise of std r × that channel's std over the
    training data (raw units), the actions none, a constant channel none; prediction and
    validation never see it."""
    rng = np.random.default_rng(0)
    scale = np.array([0.01, 1.0, 100.0, 0.0])  # channel 3 is constant
    eps = []
    for i in range(8):
        s = rng.normal(size=(301, 4)).cumsum(0) * scale + [0.0, 5.0, -3.0, 2.0]
        eps.append(Episode(states=s, actions=rng.normal(size=(300, 2)) * [1.0, 10.0], times=np.arange(301) * 0.1,
                           name=f"e{i}"))
    ds = TransitionDataset(eps)
    r = 0.2
    m = EnsembleDynamics(4, 2, ensemble=1, hidden=(8,), noise_to_signal=r, seed=0)
    seen = []
    noisy = m._noisy_batch

    def record(xb, yb, xs, ys):
        out = noisy(xb, yb, xs, ys)
        seen.append((xb, yb, *out))
        return out

    m._noisy_batch = record
    m.fit(ds, epochs=2, batch_size=600, progress=False)
    assert len(seen) == 2 * int(np.ceil(len(ds) / 600))
    dx = torch.cat([(xn - x).reshape(-1, 6) for x, _, xn, _ in seen]) * m.input_std
    dy = torch.cat([(yn - y).reshape(-1, 4) for _, y, _, yn in seen]) * m.delta_std
    raw_sx, raw_sd = ds.states.std(0), ds.deltas.std(0)
    for j in range(3):  # raw units: r × the channel's spread, whatever its scale (0.01 ... 100)
        assert float(dx[:, j].std()) == pytest.approx(r * raw_sx[j], rel=0.06)
        assert float(dy[:, j].std()) == pytest.approx(r * raw_sd[j], rel=0.06)
    assert float(dx[:, 3].abs().max()) == 0.0 and float(dy[:, 3].abs().max()) == 0.0  # constant channel
    assert float(dx[:, 4:].abs().max()) == 0.0  # actions are never noised
    # only in training: a twin without noise with the same weights predicts and validates alike
    twin = EnsembleDynamics(4, 2, ensemble=1, hidden=(8,), seed=0)
    twin.load_state_dict(m.state_dict())
    n = len(seen)
    s0, a0 = torch.from_numpy(ds.states[:50]), torch.from_numpy(ds.actions[:50])
    with torch.inference_mode():
        assert torch.equal(m.predict(s0, a0), twin.predict(s0, a0))
    assert m.evaluate(eps[:2], horizon=5) == twin.evaluate(eps[:2], horizon=5)
    assert len(seen) == n
    with pytest.raises(ValueError, match="noise_to_signal"):
        EnsembleDynamics(4, 2, noise_to_signal=float("nan"))
