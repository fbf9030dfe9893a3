"""Planners against the reference math on tiny cases, plus closed-loop point-mass runs."""

import math

import numpy as np
import pytest
import torch

from hilstack.control.planners import CEM, PDDM, Planner, RandomShooting, filtered_noise, reward_weighted_mean


def identity_dynamics(state, action):
    return state.clone()


def zero_cost(states, actions):
    return torch.zeros(states.shape[0], states.shape[1])


# -- noise scale ---------------------------------------------------------------------------------
def test_pddm_white_noise_std_is_sigma():
    p = PDDM(-100.0, 100.0, horizon=5, samples=20000, beta=1.0, sigma=0.3, action_dim=2, seed=1)
    a = p.sample(torch.zeros(5, 2))
    assert a.std().item() == pytest.approx(0.3, rel=0.03)
    assert a.mean().abs().item() < 0.01


def test_pddm_filtered_noise_variance_matches_recursion():
    beta, sigma, H = 0.7, 0.5, 12
    p = PDDM(-100.0, 100.0, horizon=H, samples=40000, beta=beta, sigma=sigma, action_dim=1, seed=2)
    a = p.sample(torch.zeros(H, 1))[..., 0]
    std_t = a.std(dim=0)
    for t in range(H):
        expected = sigma * beta * math.sqrt(sum((1 - beta) ** (2 * k) for k in range(t + 1)))
        assert std_t[t].item() == pytest.approx(expected, rel=0.04)
    stationary = sigma * math.sqrt(beta / (2 - beta))
    assert std_t[-1].item() == pytest.approx(stationary, rel=0.04)
    # neighbouring steps are positively correlated (the point of the filter)
    corr = torch.corrcoef(torch.stack([a[:, -2], a[:, -1]]))[0, 1].item()
    assert corr == pytest.approx(1 - beta, abs=0.03)


def test_filtered_noise_function_matches_planner_sampling():
    u = torch.randn(7, 5, 3, generator=torch.Generator().manual_seed(0))
    n = filtered_noise(u, 0.4)
    manual = torch.zeros(7, 3)
    for t in range(5):
        manual = 0.4 * u[:, t] + 0.6 * manual
        assert torch.allclose(n[:, t], manual)


def test_cem_first_iteration_std_is_sigma():
    p = CEM(-100.0, 100.0, horizon=4, samples=20000, elites=10, iterations=1, sigma=[0.2, 2.0],
            action_dim=2, seed=3)
    seen = {}

    def cost(states, actions):
        seen["a"] = actions.clone()
        return torch.zeros(1, actions.shape[0])

    p(identity_dynamics, cost, np.zeros(1))
    std = seen["a"].reshape(-1, 2).std(dim=0)
    assert std[0].item() == pytest.approx(0.2, rel=0.03)
    assert std[1].item() == pytest.approx(2.0, rel=0.03)


# -- elites, weights, argmin ------------------------------------------------------------------------
def test_cem_elites_are_true_topk_by_cost():
    N, K = 64, 5
    gen = torch.Generator().manual_seed(4)
    # adversarial: costs unrelated to sample index order; the elites sit at scattered indices
    perm = torch.randperm(N, generator=gen)
    rank_cost = torch.empty(N)
    rank_cost[perm] = torch.arange(N, dtype=torch.float32)
    elite_idx = perm[:K]
    seen = {}

    def cost(states, actions):
        seen["a"] = actions.clone()
        return rank_cost.unsqueeze(0)

    p = CEM(-1.0, 1.0, horizon=3, samples=N, elites=K, iterations=1, action_dim=2, seed=5)
    action = p(identity_dynamics, cost, np.zeros(1))
    expected_mean = seen["a"][elite_idx].mean(dim=0)
    assert torch.allclose(p.last_plan, expected_mean, atol=1e-6)
    np.testing.assert_allclose(action, expected_mean[0].numpy(), atol=1e-6)
    # and not the first K by index
    assert not torch.allclose(p.last_plan, seen["a"][:K].mean(dim=0), atol=1e-3)


def test_pddm_weighted_mean_matches_hand_computation():
    gamma = 2.0
    acts = torch.tensor([[[0.1]], [[0.5]], [[-0.3]]])  # N=3, H=1, A=1
    rewards = torch.tensor([1.0, 2.0, 0.5])
    w = [math.exp(gamma * r) for r in rewards.tolist()]
    hand = sum(wi * a for wi, a in zip(w, [0.1, 0.5, -0.3], strict=True)) / sum(w)
    assert reward_weighted_mean(acts, rewards, gamma).item() == pytest.approx(hand, rel=1e-6)
    # large rewards do not overflow (max-subtraction) and give the same answer
    assert reward_weighted_mean(acts, rewards + 500.0, gamma).item() == pytest.approx(hand, rel=1e-5)


def test_pddm_planner_returns_weighted_mean_of_its_samples():
    gamma = 0.7
    seen = {}

    def cost(states, actions):
        seen["a"] = actions.clone()
        c = (actions[:, :, 0] - 0.4).pow(2).sum(-1)  # [N]
        seen["c"] = c
        return c.unsqueeze(0)

    p = PDDM(-1.0, 1.0, horizon=3, samples=6, gamma=gamma, beta=0.6, sigma=0.5, action_dim=1, seed=6)
    p(identity_dynamics, cost, np.zeros(1))
    a, r = seen["a"].double(), -seen["c"].double()
    w = torch.exp(gamma * r)
    hand = (w[:, None, None] * a).sum(0) / w.sum()
    assert torch.allclose(p.last_plan.double(), hand, atol=1e-6)


def test_random_shooting_returns_first_action_of_best_sequence():
    seen = {}

    def cost(states, actions):
        seen["a"] = actions.clone()
        c = torch.rand(actions.shape[0], generator=torch.Generator().manual_seed(9))
        seen["c"] = c
        return c.expand(2, -1)  # two members, same cost

    p = RandomShooting([-1.0, 0.0], [1.0, 2.0], horizon=4, samples=50, seed=7)
    action = p(identity_dynamics, cost, np.zeros(3))
    best = int(torch.argmin(seen["c"]))
    np.testing.assert_allclose(action, seen["a"][best, 0].numpy())
    assert torch.equal(p.last_plan, seen["a"][best])
    # uniform samples cover the bounds
    a = seen["a"].reshape(-1, 2)
    assert a[:, 0].min() >= -1 and a[:, 0].max() <= 1 and a[:, 1].min() >= 0 and a[:, 1].max() <= 2
    assert a[:, 1].min() < 0.2 and a[:, 1].max() > 1.8


# -- warm start, ensemble averaging, bounds -------------------------------------------------------
@pytest.mark.parametrize("cls", [CEM, PDDM])
def test_warm_start_shifts_the_mean(cls):
    def cost(states, actions):
        target = torch.linspace(-0.5, 0.5, actions.shape[1])
        return (actions[..., 0] - target).pow(2).sum(-1).unsqueeze(0)

    p = cls(-1.0, 1.0, horizon=5, samples=200, action_dim=1, seed=8)
    p(identity_dynamics, cost, np.zeros(1))
    plan = p.last_plan.clone()
    assert torch.allclose(p.mean[:-1], plan[1:])
    assert torch.allclose(p.mean[-1], plan[-1])
    p.reset()
    assert torch.allclose(p.mean, torch.zeros(5, 1))


def test_ensemble_cost_is_averaged_over_members_and_risk_term():
    # member 0 likes action +1, member 1 likes -1 (twice as strongly): the average prefers -1
    def dynamics(state, action):
        st = state if state.dim() == 3 else state.expand(2, -1, -1)
        return st + action[..., :1]

    def cost(states, actions):
        u = actions[:, 0, 0]
        return torch.stack([(u - 1).abs(), 2 * (u + 1).abs()])

    p = RandomShooting(-1.0, 1.0, horizon=1, samples=400, action_dim=1, seed=10)
    a = p(dynamics, cost, np.zeros(1))
    assert a[0] < -0.9
    u = p._buffers["actions"][:, 0, 0]
    expected = ((u - 1).abs() + 2 * (u + 1).abs()) / 2
    assert torch.allclose(p.last_costs, expected)
    assert p.last_predicted_states.shape == (2, 2, 1)
    # risk term: mean + k*std over members
    pr = RandomShooting(-1.0, 1.0, horizon=1, samples=400, action_dim=1, seed=10, risk_k=1.5)
    pr(dynamics, cost, np.zeros(1))
    c = torch.stack([(u - 1).abs(), 2 * (u + 1).abs()])
    assert torch.allclose(pr.last_costs, c.mean(0) + 1.5 * c.std(0, unbiased=False))


@pytest.mark.parametrize("cls", [RandomShooting, CEM, PDDM])
def test_actions_respect_bounds(cls):
    low, high = np.array([-0.2, 0.5]), np.array([0.1, 0.7])
    seen = []

    def cost(states, actions):
        seen.append(actions.clone())
        return -actions.sum(dim=(1, 2)).unsqueeze(0) * 100  # pushes toward (and past) the upper bound

    kwargs = {"sigma": 5.0} if cls is not RandomShooting else {}
    p = cls(low, high, horizon=3, samples=64, seed=11, **kwargs)
    for _ in range(3):
        a = p(identity_dynamics, cost, np.zeros(2))
        assert np.all(a >= low - 1e-6) and np.all(a <= high + 1e-6)
    for s in seen:
        assert torch.all(s >= torch.tensor(low, dtype=torch.float32) - 1e-6)
        assert torch.all(s <= torch.tensor(high, dtype=torch.float32) + 1e-6)
    assert torch.all(p.last_plan <= torch.tensor(high, dtype=torch.float32) + 1e-6)


def test_rollout_shapes_and_single_model_dynamics():
    calls = []

    def dyn(state, action):
        calls.append(tuple(state.shape))
        return state + action  # [N, S]: a single model

    p = RandomShooting(-1.0, 1.0, horizon=3, samples=5, action_dim=2, seed=0)
    actions = torch.ones(5, 3, 2)
    with torch.inference_mode():
        st = p.rollout(dyn, torch.zeros(2), actions)
    assert st.shape == (1, 5, 4, 2)
    assert torch.allclose(st[0, :, -1], torch.full((5, 2), 3.0))
    assert calls == [(5, 2)] * 3


def test_seeded_planner_is_reproducible_after_reset():
    def cost(states, actions):
        return (states[..., -1, 0] - 0.3).abs()

    p = PDDM(-1.0, 1.0, horizon=4, samples=50, action_dim=1, seed=12)
    dyn = lambda s, a: s + a  # noqa: E731
    a1 = [p(dyn, cost, np.zeros(1)) for _ in range(3)]
    p.reset()
    a2 = [p(dyn, cost, np.zeros(1)) for _ in range(3)]
    np.testing.assert_array_equal(np.stack(a1), np.stack(a2))


def test_invalid_config_is_rejected():
    with pytest.raises(ValueError):
        CEM(-1.0, 1.0, samples=10, elites=20, action_dim=1)
    with pytest.raises(ValueError):
        PDDM(-1.0, 1.0, beta=0.0, action_dim=1)
    with pytest.raises(ValueError):
        Planner(1.0, -1.0, action_dim=1)


# -- closed loop: 1-D point mass with known linear dynamics ---------------------------------------
DT = 0.1


def point_mass(state, action):
    """x' = x + dt v, v' = 0.9 v + dt u (u in [-1, 1]); works for [N,2] and [E,N,2]."""
    x, v = state[..., 0], state[..., 1]
    u = action[..., 0]
    return torch.stack([x + DT * v, 0.9 * v + DT * u], dim=-1)


def goal_cost(states, actions):
    x, v = states[..., 1:, 0], states[..., 1:, 1]
    return ((x - 1.0) ** 2 + 0.1 * v**2).sum(-1)


@pytest.mark.parametrize(
    "make",
    [
        lambda: RandomShooting(-1.0, 1.0, horizon=10, samples=300, action_dim=1, seed=0),
        lambda: CEM(-1.0, 1.0, horizon=10, samples=100, elites=10, iterations=3, action_dim=1, seed=0),
        lambda: PDDM(-1.0, 1.0, horizon=10, samples=100, gamma=10.0, beta=0.7, sigma=0.5, action_dim=1, seed=0),
    ],
    ids=["random_shooting", "cem", "pddm"],
)
def test_point_mass_reaches_goal(make):
    planner = make()
    state = np.zeros(2, dtype=np.float32)
    for _ in range(120):
        a = planner(point_mass, goal_cost, state)
        assert a.shape == (1,) and -1 <= a[0] <= 1
        state = point_mass(torch.from_numpy(state), torch.from_numpy(a)).numpy()
    assert abs(state[0] - 1.0) < 0.1
    assert abs(state[1]) < 0.2


# -- wrong versions the tests above let through ----------------------------------------------------
def member_drift_dynamics(drift):
    """An ensemble whose member e moves by ``a + drift[e]`` per step, with a member-specific
    nonlinearity (squared state) so that averaging members changes the result."""
    E = drift.shape[0]

    def dyn(state, action):
        st = state if state.dim() == 3 else state.expand(E, -1, -1)
        return st + action + drift.view(E, 1, 1) + 0.1 * drift.view(E, 1, 1) * st**2
    return dyn


@pytest.mark.parametrize("cls", [RandomShooting, CEM, PDDM])
def test_each_member_is_rolled_out_on_its_own_over_the_horizon(cls):
    """Members never see each other's predictions: collapsing the ensemble to its mean
    after each step would agree with this only at h = 1."""
    drift = torch.tensor([-0.5, 0.1, 0.9])
    dyn = member_drift_dynamics(drift)
    H, N = 4, 6
    p = cls(-1.0, 1.0, horizon=H, samples=N, action_dim=1, seed=0, **({"elites": 2} if cls is CEM else {}))
    actions = torch.rand(N, H, 1, generator=torch.Generator().manual_seed(1)) * 2 - 1
    with torch.inference_mode():
        st = p.rollout(dyn, torch.zeros(1), actions)
    for e in range(3):
        s = torch.zeros(N, 1)
        for h in range(H):
            s = s + actions[:, h] + drift[e] + 0.1 * drift[e] * s**2
            assert torch.allclose(st[e, :, h + 1], s, atol=1e-6), (e, h)
    # the planner scores those independent rollouts: cost averaged over members
    seen = {}

    def cost(states, acts):
        seen["states"] = states.clone()
        return states[..., -1, 0] ** 2

    p.reset()
    p(dyn, cost, np.zeros(1))
    final = seen["states"][:, :, -1, 0]
    assert final.std(dim=0).min() > 0.5  # the members stay apart at h = H


def test_cem_refits_sigma_to_the_elites_every_iteration():
    """Reference math on a horizon-4, 2-D case: the samples of iteration i+1 have the
    (population) std and mean of the elites of iteration i, per step and dimension."""
    H, N, K = 4, 20000, 1000
    target = torch.tensor([[0.3, -0.2], [0.1, 0.4], [-0.3, 0.0], [0.2, 0.2]])
    seen = []

    def cost(states, actions):
        seen.append(actions.clone())
        return ((actions - target) ** 2).sum(dim=(1, 2)).unsqueeze(0)

    p = CEM(-100.0, 100.0, horizon=H, samples=N, elites=K, iterations=3, sigma=1.0, action_dim=2, seed=5)
    p(identity_dynamics, cost, np.zeros(1))
    assert len(seen) == 3
    for i in range(2):
        a = seen[i]
        c = ((a - target) ** 2).sum(dim=(1, 2))
        elite = a[torch.topk(c, K, largest=False).indices]
        mu, sd = elite.mean(0), elite.std(0, unbiased=False)
        nxt = seen[i + 1]
        assert torch.allclose(nxt.std(0), sd, rtol=0.05), (i, nxt.std(0), sd)
        assert torch.allclose(nxt.mean(0), mu, atol=0.05 * sd.max().item() + 1e-3)
    # σ really shrinks: the elites of a quadratic bowl are much tighter than the prior
    assert seen[2].std(0).max() < 0.5


def test_random_shooting_samples_within_the_reachable_set():
    r = torch.tensor([0.2, 0.5])
    p = RandomShooting(-1.0, 1.0, horizon=4, samples=3000, action_dim=2, seed=3, max_step=r)
    seen = []

    def cost(states, actions):
        seen.append(actions.clone())
        return -actions[:, :, 0].sum(1).unsqueeze(0)  # prefers the largest first leg command

    a0 = p(identity_dynamics, cost, np.zeros(1))
    first = seen[0]
    # after reset the first step may be anywhere in the bounds, later steps move at most r
    assert first[:, 0].min() < -0.9 and first[:, 0].max() > 0.9
    steps = (first[:, 1:] - first[:, :-1]).abs()
    assert torch.all(steps <= r + 1e-6)
    # each step is uniform on [prev - r, prev + r] ∩ bounds: it uses the whole interval
    assert torch.all(steps.reshape(-1, 2).max(0).values > 0.95 * r)
    a1 = p(identity_dynamics, cost, np.zeros(1))
    second = seen[1]
    assert torch.all((second[:, 0] - torch.as_tensor(a0)).abs() <= r + 1e-6)
    assert a1[0] > a0[0]  # it climbs toward the preferred command at the rate limit
    assert torch.all(second >= -1.0) and torch.all(second <= 1.0)
    p.reset()
    p(identity_dynamics, cost, np.zeros(1))
    assert seen[2][:, 0, 0].min() < -0.9  # reset forgets the previous action
    with pytest.raises(ValueError, match="max_step"):
        RandomShooting(-1.0, 1.0, action_dim=2, max_step=0.0)


# -- moving in time: the planner owns its shift -------------------------------------------------
def test_shift_moves_the_warm_start_along_the_last_plan():
    """After a plan the warm start is ``plan[1:]`` (last step repeated); ``shift(n)`` (the plan
    was applied n periods late) moves it to ``plan[n+1:]`` and anchors a rate-limited sampler
    at ``plan[n]``, the step acting now; shifts add up; past the end the last step repeats."""
    H = 5
    for cls, kw in ((CEM, dict(elites=2, iterations=1)), (PDDM, dict(gamma=1.0, beta=1.0))):
        p = cls(-5.0, 5.0, horizon=H, samples=8, action_dim=1, seed=0, **kw)
        p.shift(3)  # before any plan: nothing to move along
        assert torch.equal(p.mean, ((p.action_low + p.action_high) / 2).expand(H, -1))
        p(identity_dynamics, zero_cost, np.zeros(1))
        plan = p.last_plan.clone()
        assert torch.equal(p.mean, torch.cat([plan[1:], plan[-1:]]))
        p.shift(2)
        assert torch.equal(p.mean, torch.cat([plan[3:]] + [plan[-1:]] * 3))
        if cls is PDDM:
            assert torch.equal(p.previous, plan[2])
        p.shift(1)
        assert torch.equal(p.mean, torch.cat([plan[4:]] + [plan[-1:]] * 4))
        p.shift(10)
        assert torch.equal(p.mean, plan[-1:].expand(H, -1))
        with pytest.raises(ValueError, match="n >= 0"):
            p.shift(-1)
    rs = RandomShooting(-1.0, 1.0, horizon=H, samples=8, action_dim=1, seed=0, max_step=0.1)
    rs(identity_dynamics, zero_cost, np.zeros(1))
    rs.shift(2)
    assert torch.equal(rs.previous, rs.last_plan[2])


def test_a_late_plan_in_the_realtime_loop_shifts_the_planner():
    """run_realtime tells the policy how many cycles its plan missed (MpcPolicy.shift ->
    Planner.shift), so the next plan is warm-started from where the robot now is on it."""
    from hilstack.control.policies import MpcPolicy

    class Model:
        def predict(self, s, a):
            return s.clone()

    p = CEM(-1.0, 1.0, horizon=4, samples=8, elites=2, action_dim=1, seed=0)
    pol = MpcPolicy(Model(), p, zero_cost)
    pol(np.zeros(1))
    plan = p.last_plan.clone()
    pol.shift(2)
    assert torch.equal(p.mean, torch.cat([plan[3:]] + [plan[-1:]] * 3))
