"""The calibration model's contract (calibration/model_api.py): every concrete model satisfies
:class:`Model` and declares its optional capabilities; a model that declares a capability and lacks
its method cannot be built (one line naming the model and the method); the registry refuses a
model that lacks a required member; the typed accessors (a sim backend's calibration bench, the
network inside a dynamics checkpoint) answer for what they name and refuse the rest."""

from __future__ import annotations

import pytest
import torch

from hilstack.calibration import model_api as api
from hilstack.calibration.model_api import Model, NominalModel
from hilstack.calibration.models import MODELS, AxisModel, FittedAxis, get_model

#: every optional capability of a model, with the members it makes a model have
CAPABILITIES = {
    api.LoadsEpisodes: ("load_episodes",),
    api.BatchLosses: ("episode_losses", "oob_losses"),
    api.OwnDetectionLimits: ("detection_limits",),
    api.ResidualRows: ("residual_rows",),
    api.OwnPlots: ("plots",),
    api.ExportsSimParams: ("export",),
    api.ExportsAugmented: ("export_augmented",),
    api.CountsRollouts: ("n_rollouts",),
    api.DescribesVelocity: ("velocity_source",),
}


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    from hilstack.calibration.synthetic_learned import train_checkpoint

    torch.set_num_threads(1)
    return train_checkpoint(tmp_path_factory.mktemp("api") / "m.pt", n_episodes=2, steps=20, epochs=1)


def _models(checkpoint):
    return {"axis": get_model("axis"), "velociroach": get_model("velociroach"),
            "checkpoint": get_model(str(checkpoint))}


#: what each model of the repository declares (the report's and the selection's branches follow it)
DECLARED = {
    "axis": {api.BatchLosses},
    "velociroach": {api.OwnDetectionLimits, api.ResidualRows, api.OwnPlots, api.ExportsSimParams,
                    api.CountsRollouts},
    "checkpoint": {api.LoadsEpisodes, api.OwnDetectionLimits, api.ResidualRows, api.OwnPlots,
                   api.ExportsAugmented, api.DescribesVelocity},
}


def test_every_registered_model_satisfies_the_protocol_and_declares_its_capabilities(checkpoint):
    models = _models(checkpoint)
    assert set(models) == set(MODELS)  # a model added to the registry is added here too
    for name, m in models.items():
        assert isinstance(m, Model) and api.missing_members(m) == [], (name, api.missing_members(m))
        assert isinstance(m, NominalModel), name
        for flag in ("segmentable", "pair_tests", "reports_bounds", "shift_interval_to_refined"):
            assert isinstance(getattr(m, flag), bool), (name, flag)
        declared = {c for c in CAPABILITIES if c in type(m).__mro__}  # named among its bases
        assert declared == DECLARED[name], name
        # what the callers' isinstance sees is what the class declares: no undeclared method is used
        assert {c for c in CAPABILITIES if isinstance(m, c)} == declared, name
    assert (models["axis"].segmentable, models["axis"].pair_tests, models["axis"].reports_bounds) == (True, True, True)
    assert models["velociroach"].shift_interval_to_refined and not models["checkpoint"].shift_interval_to_refined


def test_fitted_models_satisfy_their_protocol(checkpoint):
    from hilstack.calibration.synthetic import SynthConfig, generate

    ax = get_model("axis")
    fitted = ax.fit(ax.prepare(generate(SynthConfig(n_episodes=2, duration_s=2.0, seed=0))), [])
    assert isinstance(fitted, FittedAxis) and isinstance(fitted, api.FittedModel)
    assert isinstance(fitted, api.PhaseAlong)  # the bootstrap measures a periodic load along its phase
    for p in ax.prepare(generate(SynthConfig(n_episodes=1, duration_s=2.0, seed=1))):
        assert isinstance(p, api.PreparedEpisode)


class _NoScore(NominalModel):
    """Every member of Model but ``score``."""

    name = "noscore"
    catalogue: dict = {}
    look_alikes: dict = {}

    def prepare(self, episodes): ...
    def fit(self, episodes, effects, **kw): ...
    def candidate_effects(self, episodes, accepted=()): ...
    def norms(self, pool): ...
    def episode_loss(self, prep, fitted, horizon, nm): ...
    def oob_loss(self, prep, fitted, nm): ...
    def channel_sd(self, preps): ...


class _Plain(_NoScore):
    """A complete model that declares no capability."""

    name = "plain"

    def score(self, prep, fitted, horizon): ...


@pytest.mark.parametrize("capability", list(CAPABILITIES), ids=lambda c: c.__name__)
def test_a_declared_capability_without_its_method_fails_at_construction(capability):
    """The declaration is checked when the model is built, in one line naming it and the member."""
    assert isinstance(_Plain(), Model) and not isinstance(_Plain(), capability)
    Broken = type("BrokenModel", (_Plain, capability), {})
    with pytest.raises(TypeError) as e:
        Broken()
    msg = str(e.value)
    assert "\n" not in msg and "BrokenModel" in msg, msg
    assert all(member in msg for member in CAPABILITIES[capability]), msg


def test_a_declared_capability_with_its_method_is_used():
    """Declaring and implementing: isinstance answers yes (what report.py and selection.py ask)."""

    class WithPlots(AxisModel, api.OwnPlots):
        def plots(self, out, sel, preps, pool, test) -> None:
            return None

    assert isinstance(WithPlots(), api.OwnPlots) and not isinstance(AxisModel(), api.OwnPlots)


def test_the_registry_refuses_a_model_without_a_required_member(monkeypatch):
    monkeypatch.setitem(MODELS, "noscore", lambda **kw: _NoScore())
    with pytest.raises(TypeError, match=r"^nominal model 'noscore' \(_NoScore\) lacks score of the Model protocol"):
        get_model("noscore")
    assert not isinstance(_NoScore(), Model)
    monkeypatch.setitem(MODELS, "plain", lambda **kw: _Plain())
    assert isinstance(get_model("plain"), _Plain)


def test_calibration_bench_is_a_typed_capability_of_sim_backends():
    from hilstack.calibration.mjcf_robot import CalibrationBench
    from hilstack.drivers.registry import resolve

    assert issubclass(resolve("widowx", "sim"), CalibrationBench)
    assert issubclass(resolve("shadow_hand", "sim"), CalibrationBench)
    assert not issubclass(resolve("velociroach", "sim"), CalibrationBench)


def test_record_excitation_refuses_a_robot_without_a_bench(tmp_path):
    from hilstack.calibration.robot_rig import record_excitation

    with pytest.raises(ValueError, match=r"robot 'velociroach': its sim backend has no calibration_bench\(\)"):
        record_excitation(tmp_path / "x.mcap", duration_s=0.1, robot="velociroach")
    assert not (tmp_path / "x.mcap").exists()


def test_ensemble_of_unwraps_a_body_frame_model_and_refuses_anything_else():
    from hilstack.learning.dynamics import EnsembleDynamics
    from hilstack.learning.frames import BodyFrameDynamics, ensemble_of

    names = ["x", "y", "vx", "vy", "cos_yaw", "sin_yaw"]
    net = EnsembleDynamics(len(names), 2, 1, [8], state_names=names)
    assert ensemble_of(net) is net
    assert ensemble_of(BodyFrameDynamics(net, names)) is net
    with pytest.raises(TypeError, match="^expected an EnsembleDynamics or a BodyFrameDynamics, got dict$"):
        ensemble_of({})
