"""Nominal models for calibration: the axis model and the registry.

A nominal model is refit together with each candidate effect (grey box), replays logged
commands open loop and predicts one step ahead. The selection code
(:mod:`hilstack.calibration.selection`) only talks to the :class:`Model` / :class:`FittedModel`
protocol (:mod:`hilstack.calibration.model_api`, re-exported here): fitting on (weighted)
episodes, a per-episode held-out loss, a cheap out-of-bag loss, the model's effect catalogue
and look-alike table; what a model offers beyond that it declares by the optional
capabilities there.

Registered: ``axis`` (:mod:`hilstack.calibration.axis`), ``velociroach`` (the MuJoCo backend,
:mod:`hilstack.calibration.velociroach`), ``checkpoint`` (a learned dynamics checkpoint, where an
effect is a missing input: :mod:`hilstack.calibration.learned`; needs ``checkpoint=PATH``, or pass
the ``.pt`` path as the model name).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hilstack.calibration import axis
from hilstack.calibration.data import Recording
from hilstack.calibration.effects import CATALOGUE, LOOK_ALIKES
from hilstack.calibration.model_api import (
    BatchLosses,
    FittedModel,
    Model,
    NominalModel,
    PhaseAlong,
    require_model,
)

__all__ = ["AxisModel", "FittedAxis", "FittedModel", "Model", "ModelNotAvailable", "UnknownModel", "get_model",
           "load_model", "save_model"]


class ModelNotAvailable(RuntimeError):
    """The requested nominal model exists in the registry but its backend is missing."""


class UnknownModel(ValueError):
    """The requested nominal model name is not registered."""


@dataclass
class FittedAxis(PhaseAlong):
    """The axis model with its parameters (see :mod:`hilstack.calibration.axis`)."""

    params: axis.AxisParams

    @property
    def effects(self) -> list[str]:
        return self.params.effects

    def primary(self, name: str) -> float:
        return self.params.primary(name)

    @property
    def at_bound(self) -> dict[str, float]:
        """Hyper-parameters stuck at the edge of their (widened) search grid."""
        return self.params.at_bound

    def effect_params(self, name: str) -> dict[str, float]:
        return self.params.effect_params(name)

    def primary_along(self, name: str, ref: FittedAxis) -> float:
        """Primary of a position-periodic load along ``ref``'s phase (see AxisParams.primary_along)."""
        return self.params.primary_along(name, ref.params)

    def predict_one_step(self, episode: axis.Prepared | Recording) -> dict:
        p = episode if isinstance(episode, axis.Prepared) else self._prep(episode)
        return axis.predict_one_step(p, self.params)

    def simulate(self, episode: axis.Prepared | Recording, horizon: int | None = None) -> dict:
        """Open-loop replay of the logged commands; whole episode when ``horizon`` is None."""
        p = episode if isinstance(episode, axis.Prepared) else self._prep(episode)
        if horizon is None:
            h = p.n - 2 * p.margin - 2
            import numpy as np

            return axis.simulate_windows(p, self.params, h, starts=np.array([p.margin]))
        return axis.simulate_windows(p, self.params, horizon)

    def _prep(self, ep: Recording) -> axis.Prepared:
        return axis.prepare([ep], sg_window=self.params.sg_window)[0]

    def to_dict(self) -> dict:
        return {"model": "axis", "params": self.params.to_dict()}


#: Fewest radians the position must span before a gravity (sine) load is a candidate.
GRAVITY_MIN_SPAN_RAD = 1.5
#: A position passed in both directions over less than this fraction of the visited range is a
#: one-way travel (a distance driven), not a joint angle: a gravity sine of it is not offered.
TWO_WAY_MIN_FRACTION = 0.1


def two_way_fraction(episodes: list[axis.Prepared], n_bins: int = 50) -> float:
    """Fraction of the visited position bins (``n_bins`` over the whole range) passed both moving up
    and moving down. A swinging joint or a stroke back and forth: near 1; a vehicle's distance
    travelled forward: near 0 (odometry noise at standstill does not count: only moving rows)."""
    xs = np.concatenate([p.ep.x for p in episodes])
    lo, hi = float(xs.min()), float(xs.max())
    if not hi > lo:
        return 0.0
    up, down = np.zeros(n_bins, bool), np.zeros(n_bins, bool)
    for p in episodes:
        v, x, mv = p.v_obs, p.ep.x, p.moving
        b = np.clip(((x - lo) / (hi - lo) * n_bins).astype(int), 0, n_bins - 1)
        up[b[mv & (v > 0)]] = True
        down[b[mv & (v < 0)]] = True
    visited = up | down
    return float((up & down).sum() / max(1, visited.sum()))


class AxisModel(NominalModel, BatchLosses):
    """Single-axis drive J·dv/dt = k_u·u − b·v, identified as dv/dt = a·u − c·v + effects."""

    name = "axis"
    catalogue = CATALOGUE
    look_alikes = LOOK_ALIKES
    #: long recordings may be cut into contiguous segments (windows start from measured states)
    segmentable = True
    #: cheap fits: test the best candidates in pairs, and flag estimates at a search bound
    pair_tests = True
    reports_bounds = True

    def __init__(self, k_u: float | None = None, sg_window: int | None = None):
        self.k_u = k_u
        self.sg_window = sg_window

    def norms(self, pool: list[axis.Prepared]):
        from hilstack.calibration.selection import compute_norms

        return compute_norms(pool)

    def episode_loss(self, prep: axis.Prepared, fitted: FittedAxis, horizon: int, nm):
        from hilstack.calibration.selection import episode_loss

        return episode_loss(axis.score(prep, fitted.params, horizon), nm)

    def oob_loss(self, prep: axis.Prepared, fitted: FittedAxis, nm):
        """Per-channel squared errors (one-step and open-loop windows), as the selection scores them.

        Sums, not means, so that the bootstrap can add them over out-of-bag episodes.
        """
        import numpy as np

        s = axis.score(prep, fitted.params, max(nm.horizon, 2))
        return np.array([s.one_sse["x"] / nm.one_x, s.one_sse["v"] / nm.one_v,
                         s.multi_sse["x"] / nm.multi_x, s.multi_sse["v"] / nm.multi_v])

    def score(self, prep: axis.Prepared, fitted: FittedAxis, horizon: int) -> axis.Scores:
        return axis.score(prep, fitted.params, horizon)

    def episode_losses(self, pairs, horizon: int, nm) -> list:
        """:meth:`episode_loss` of many (episode, fitted) pairs, replayed in one vectorised batch."""
        from hilstack.calibration.selection import episode_loss

        scores = axis.score_many([(p, f.params) for p, f in pairs], horizon)
        return [episode_loss(s, nm) for s in scores]

    def oob_losses(self, pairs, nm) -> list:
        """:meth:`oob_loss` of many (episode, fitted) pairs, replayed in one vectorised batch."""
        import numpy as np

        scores = axis.score_many([(p, f.params) for p, f in pairs], max(nm.horizon, 2))
        return [np.array([s.one_sse["x"] / nm.one_x, s.one_sse["v"] / nm.one_v,
                          s.multi_sse["x"] / nm.multi_x, s.multi_sse["v"] / nm.multi_v]) for s in scores]

    def channel_sd(self, preps: list[axis.Prepared]) -> dict[str, dict[str, float]]:
        """Report normalizers: std of the one-step increment and of the channel itself."""
        import numpy as np

        dx = np.concatenate([np.diff(p.ep.x) for p in preps])
        dv = np.concatenate([np.diff(p.v_obs) for p in preps])
        return {
            "one": {"x": float(np.std(dx)) + 1e-300, "v": float(np.std(dv)) + 1e-300},
            "multi": {"x": float(np.std(np.concatenate([p.ep.x for p in preps]))) + 1e-300,
                      "v": float(np.std(np.concatenate([p.v_obs for p in preps]))) + 1e-300},
        }

    def prepare(self, episodes: list[Recording]) -> list[axis.Prepared]:
        return axis.prepare(episodes, sg_window=self.sg_window)

    def fit(self, episodes: list[axis.Prepared], effects: list[str], weights=None, refine: bool = True,
            start: FittedAxis | None = None, search: list[str] | None = None) -> FittedAxis:
        return FittedAxis(axis.fit_axis(episodes, effects, weights=weights, refine=refine, k_u=self.k_u,
                                        start=None if start is None else start.params, search=search))

    def candidate_effects(self, episodes: list[axis.Prepared], accepted: tuple[str, ...] = ()
                          ) -> tuple[list[str], dict[str, str]]:
        """(testable effects given the already accepted ones, {skipped effect: reason})."""
        has = {
            # a logged velocity the model uses as its state (not replaced by the position derivative)
            "v": all(p.ep.v_meas is not None and p.kernel is None for p in episodes),
            "vbat": all(p.ep.vbat_v is not None for p in episodes),
            "m": all(p.ep.payload is not None for p in episodes),
        }
        names, skipped = [], {}
        xs = [p.ep.x for p in episodes]
        span_x = float(max(x.max() for x in xs) - min(x.min() for x in xs))
        for name, spec in CATALOGUE.items():
            if spec.absorbed_by_nominal:
                skipped[name] = "absorbed by the nominal refit: " + spec.absorbed_by_nominal
            elif name in ("stribeck_friction", "asymmetric_friction") and "coulomb_friction" not in accepted:
                # Both refine a Coulomb level (a breakaway peak on top of it, a direction-dependent
                # part of it). Alone, the asymmetric part is an offset acting only in motion, and
                # Coulomb + asymmetry is Coulomb + offset on every moving row: on real data (EMPS)
                # that pair is the physical reading, so the symmetric level comes first.
                skipped[name] = "tested once coulomb_friction is accepted (it refines the Coulomb level)"
            elif name == "gravity_load" and span_x < GRAVITY_MIN_SPAN_RAD:
                # Over a short stroke sin(x - q0) is an offset plus a spring: nothing to tell it by.
                skipped[name] = (f"positions span only {span_x:.3g} (< {GRAVITY_MIN_SPAN_RAD:.3g} rad): a sine load "
                                 "cannot be told from an offset and a spring; needs a rotary joint moving over a "
                                 "wide angle, x in rad")
            elif name == "gravity_load" and (two_way := two_way_fraction(episodes)) < TWO_WAY_MIN_FRACTION:
                # A sine of the position is a gravity load only for an angle that swings through it;
                # a distance travelled one way (a vehicle's odometry) has no angle to load.
                skipped[name] = (f"the position is a one-way travel (passed in both directions over "
                                 f"{100 * two_way:.0f} % < {100 * TWO_WAY_MIN_FRACTION:.0f} % of its range: a "
                                 "distance, not a joint angle); a sine load of it has no physical meaning")
            elif name == "cogging" and axis.cogging_grid(episodes).size == 0:
                skipped[name] = ("the stroke is too short for two periods of a load the sample rate can resolve "
                                 f"(at least {axis.COG_MIN_TRAVEL_SAMPLES} samples of travel per period)")
            elif not all(has[n] for n in spec.needs):
                need = {"v": "a measured velocity column (v=...)", "vbat": "a battery voltage column (vbat=...)",
                        "m": "a payload column (m=...)"}
                skipped[name] = "needs " + " and ".join(need[n] for n in spec.needs)
            else:
                names.append(name)
        return names, skipped


def _mujoco_model(**kw):
    try:
        from hilstack.calibration.velociroach import VelociRoachModel
    except ImportError as e:  # mujoco or the sim backend missing from this install
        raise ModelNotAvailable(f"model 'velociroach' needs MuJoCo and hilstack.sim_backends.velociroach ({e})") from e
    return VelociRoachModel(**kw)


def _checkpoint_model(checkpoint: str | Path | None = None, **kw):
    if checkpoint is None:
        raise ModelNotAvailable(
            "model 'checkpoint' (a learned dynamics checkpoint as nominal, where an effect is a missing input) is "
            "not available without a checkpoint file: pass --model path/to/model.pt "
            "(or --model checkpoint --checkpoint PATH)"
        )
    from hilstack.calibration.learned import CheckpointModel

    return CheckpointModel(checkpoint, **kw)


MODELS = {
    "axis": lambda **kw: AxisModel(**kw),
    "velociroach": _mujoco_model,
    "checkpoint": _checkpoint_model,
}


def get_model(name: str, **kw) -> Model:
    """Instantiate a registered nominal model by name (options that are None are dropped).

    A name ending in ``.pt`` is a learned dynamics checkpoint: ``get_model("m.pt")`` is
    ``get_model("checkpoint", checkpoint="m.pt")``.
    """
    if str(name).endswith(".pt"):
        kw = {**kw, "checkpoint": name}
        name = "checkpoint"
    if name not in MODELS:
        raise UnknownModel(f"unknown model {name!r}; known models: {', '.join(sorted(MODELS))}")
    return require_model(MODELS[name](**{k: v for k, v in kw.items() if v is not None}), name)


def save_model(fitted: FittedModel, path: str | Path, extra: dict | None = None) -> Path:
    path = Path(path)
    doc = fitted.to_dict()
    if extra:
        doc.update(extra)
    path.write_text(json.dumps(doc, indent=2))
    return path


def load_model(path: str | Path) -> FittedModel:
    """Load an augmented model written by :func:`run_calibration` (``model.json``)."""
    doc = json.loads(Path(path).read_text())
    if doc.get("model") == "checkpoint":
        from hilstack.calibration.learned import load_augmented

        # the network is in model_augmented.pt next to model.json
        return load_augmented(Path(path).with_name("model_augmented.pt"))
    if doc.get("model") == "velociroach":
        from hilstack.calibration.velociroach import FittedVelociRoach

        return FittedVelociRoach.from_dict(doc)
    if doc.get("model") != "axis":
        raise UnknownModel(f"{path}: model {doc.get('model')!r} cannot be loaded (known: axis, velociroach, "
                           "checkpoint)")
    return FittedAxis(axis.AxisParams.from_dict(doc["params"]))
