"""VelociRoACH sim perturbations: typed settings, presets, switching mid-episode, defaults untouched."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilstack.configs.schema import ConfigError, load_robot, parse_model
from hilstack.sim_backends.velociroach.backend import VelociRoachSim
from hilstack.tasks.perturbations import PerturbationSettings, load_presets


def _sim(**sim) -> VelociRoachSim:
    s = VelociRoachSim.from_config(load_robot("velociroach", params={"sim": sim}))
    s.configure()
    s.activate()
    return s


def _run(sim: VelociRoachSim, steps: int, action=(8.0, 8.0), switch: dict[int, PerturbationSettings] | None = None):
    out = []
    for t in range(steps):
        if switch and t in switch:
            sim.apply_perturbations(switch[t])
        sim.write(np.array(action))
        sim.tick()
        out.append(sim.read().state.copy())
    return np.array(out)


def _yaw(states, names):
    return np.arctan2(states[:, names.index("sin_yaw")], states[:, names.index("cos_yaw")])


def test_unperturbed_settings_leave_the_physics_bit_identical():
    a, b = _sim(), _sim()
    b.apply_perturbations(PerturbationSettings())
    np.testing.assert_array_equal(_run(a, 15), _run(b, 15))


def test_heading_offset_rotates_the_reported_heading_only():
    a, b = _sim(), _sim()
    b.apply_perturbations(PerturbationSettings(heading_offset_deg=25.0))
    sa, sb = _run(a, 10), _run(b, 10)
    names = list(a.spec.state.names)
    # the same physics and noise: positions and velocities identical, heading off by 25°
    np.testing.assert_allclose(sa[:, :6], sb[:, :6], atol=1e-9)
    d = np.angle(np.exp(1j * (_yaw(sb, names) - _yaw(sa, names))))
    np.testing.assert_allclose(d, math.radians(25.0), atol=1e-6)


def test_switching_mid_episode_changes_and_restores_the_robot():
    names = None
    ref = _sim()
    names = list(ref.spec.state.names)
    base = _run(ref, 30)
    sim = _sim()
    leg = PerturbationSettings(missing_leg=["lm"])
    pert = _run(sim, 30, switch={10: leg, 20: PerturbationSettings()})
    np.testing.assert_array_equal(pert[:10], base[:10])  # before the switch: identical
    assert not np.allclose(pert[10:20], base[10:20])      # disabled leg: a different gait
    foot = [g for g in sim._leg_geoms["lm"] if sim.model.geom(g).name.endswith("foot")][0]
    assert sim.model.geom_contype[foot] != 0             # restored after the switch back
    del names


@pytest.mark.parametrize("settings, slower", [
    (PerturbationSettings(payload_kg=0.05), True),
    (PerturbationSettings(slope_deg=10.0), True),
])
def test_payload_and_uphill_slope_slow_the_robot(settings, slower):
    a, b = _sim(), _sim()
    b.apply_perturbations(settings)
    da = np.hypot(*_run(a, 20)[-1, :2])
    db = np.hypot(*_run(b, 20)[-1, :2])
    assert (db < 0.95 * da) == slower


def test_slope_tilts_gravity_and_back():
    s = _sim()
    s.apply_perturbations(PerturbationSettings(slope_deg=10.0))
    np.testing.assert_allclose(s.model.opt.gravity, [-9.81 * math.sin(math.radians(10)), 0, -9.81 * math.cos(math.radians(10))])
    s.apply_perturbations(PerturbationSettings())
    np.testing.assert_allclose(s.model.opt.gravity, [0, 0, -9.81])


def test_presets_load_and_test_conditions_lie_outside_training():
    p = load_presets("velociroach")
    assert p.heldout_terrain not in p.training_terrains and len(p.training_terrains) >= 2
    tr = p.training
    assert p.tests["slope"].slope_deg > tr.slope_deg[1]
    assert p.tests["payload"].payload_kg > tr.payload_kg[1]
    assert p.tests["miscalibration"].heading_offset_deg > tr.heading_offset_deg[1]
    assert not set(p.tests["missing_leg"].missing_leg) & set(tr.missing_leg)
    rng = np.random.default_rng(0)
    for _ in range(50):
        c = tr.sample(rng)
        assert tr.slope_deg[0] <= c.slope_deg <= tr.slope_deg[1] and len(c.missing_leg) <= 1


def test_bad_settings_name_the_field(tmp_path):
    with pytest.raises(ConfigError, match="missing_leg"):
        parse_model(PerturbationSettings, {"missing_leg": ["xx"]})
    with pytest.raises(ConfigError, match=r"slop.*unknown field"):
        parse_model(PerturbationSettings, {"slop_deg": 3})
    f = tmp_path / "p.yaml"
    f.write_text("training_terrains: [carpet]\nheldout_terrain: carpet\ntests: {}\nswitching: {conditions: [normal, x]}\n")
    with pytest.raises(ConfigError, match="p.yaml"):
        load_presets(f)
    with pytest.raises(ValueError, match="heading_offset_deg must be finite"):
        _sim().set_perturbation("heading_offset_deg", float("nan"))



def test_training_leg_speed_scale_runs_each_side_at_its_factor_and_resets():
    from hilstack.learning.adaptation.experiment import RoachSim

    env = RoachSim("carpet", 0)
    try:
        names = env.state_names
        il, ir = names.index("crank_vel_l"), names.index("crank_vel_r")

        def crank(scale):
            env.set_leg_speed_scale(*scale)
            env.start({"x": 0.0, "y": 0.0, "yaw": 0.0}, PerturbationSettings())
            s = None
            for _ in range(15):
                applied, s = env.step(np.array([0.5, 0.5], dtype=np.float32))
            return s[il], s[ir], applied

        l1, r1, a1 = crank((1.0, 1.0))
        l2, r2, a2 = crank((0.6, 1.4))
        assert l2 < 0.8 * l1 and r2 > 1.2 * r1  # the cranks follow the factor ...
        np.testing.assert_allclose(a2, a1, atol=1e-6)  # ... while the applied command reads the same
        l3, r3, _ = crank((1.0, 1.0))
        assert l3 == pytest.approx(l1, rel=0.05) and r3 == pytest.approx(r1, rel=0.05)
    finally:
        env.close()
