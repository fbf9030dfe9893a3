"""Nominal models for calibration: a small protocol and a registry.

A nominal model is refit together with each candidate effect (grey box), replays logged
commands open loop (``simulate``) and predicts one step ahead (``predict_one_step``). The
selection code only talks to this protocol, so a MuJoCo-backed model (``velociroach``,
sim_backends/velociroach) or a learned dynamics checkpoint can plug in by implementing it.

Only ``axis`` is implemented. ``velociroach`` and ``checkpoint`` are registered but raise
:class:`ModelNotAvailable` until their backends exist; they are not faked.
"""

from __future__ import annotations

import importlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from calibration import axis
from calibration.data import Episode


class ModelNotAvailable(RuntimeError):
    """The requested nominal model exists in the registry but its backend is missing."""


class UnknownModel(ValueError):
    """The requested nominal model name is not registered."""


@runtime_checkable
class FittedModel(Protocol):
    """A nominal model with fitted parameters and a set of effects."""

    effects: list[str]

    def predict_one_step(self, episode: Any) -> dict: ...

    def simulate(self, episode: Any, horizon: int) -> dict: ...

    def to_dict(self) -> dict: ...


@runtime_checkable
class Model(Protocol):
    """A nominal model family: prepares data, fits parameters together with effects."""

    name: str

    def prepare(self, episodes: list[Episode]) -> list: ...

    def fit(self, episodes: list, effects: list[str], **kw) -> FittedModel: ...

    def candidate_effects(self, episodes: list, accepted: tuple[str, ...] = ()
                          ) -> tuple[list[str], dict[str, str]]: ...


@dataclass
class FittedAxis:
    """The axis model with its parameters (see :mod:`calibration.axis`)."""

    params: axis.AxisParams

    @property
    def effects(self) -> list[str]:
        return self.params.effects

    def predict_one_step(self, episode: axis.Prepared | Episode) -> dict:
        p = episode if isinstance(episode, axis.Prepared) else self._prep(episode)
        return axis.predict_one_step(p, self.params)

    def simulate(self, episode: axis.Prepared | Episode, horizon: int | None = None) -> dict:
        """Open-loop replay of the logged commands; whole episode when ``horizon`` is None."""
        p = episode if isinstance(episode, axis.Prepared) else self._prep(episode)
        if horizon is None:
            h = p.n - 2 * p.margin - 2
            import numpy as np

            return axis.simulate_windows(p, self.params, h, starts=np.array([p.margin]))
        return axis.simulate_windows(p, self.params, horizon)

    def _prep(self, ep: Episode) -> axis.Prepared:
        return axis.prepare([ep], sg_window=self.params.sg_window)[0]

    def to_dict(self) -> dict:
        return {"model": "axis", "params": self.params.to_dict()}


class AxisModel:
    """Single-axis drive J·dv/dt = k_u·u − b·v, identified as dv/dt = a·u − c·v + effects."""

    name = "axis"

    def __init__(self, k_u: float | None = None, sg_window: int | None = None):
        self.k_u = k_u
        self.sg_window = sg_window

    def prepare(self, episodes: list[Episode]) -> list[axis.Prepared]:
        return axis.prepare(episodes, sg_window=self.sg_window)

    def fit(self, episodes: list[axis.Prepared], effects: list[str], weights=None, refine: bool = True,
            start: FittedAxis | None = None, search: list[str] | None = None) -> FittedAxis:
        return FittedAxis(axis.fit_axis(episodes, effects, weights=weights, refine=refine, k_u=self.k_u,
                                        start=None if start is None else start.params, search=search))

    def candidate_effects(self, episodes: list[axis.Prepared], accepted: tuple[str, ...] = ()
                          ) -> tuple[list[str], dict[str, str]]:
        """(testable effects given the already accepted ones, {skipped effect: reason})."""
        from calibration.effects import CATALOGUE

        has = {
            "v": all(p.ep.v_meas is not None for p in episodes),
            "vbat": all(p.ep.vbat_v is not None for p in episodes),
            "m": all(p.ep.payload is not None for p in episodes),
        }
        names, skipped = [], {}
        for name, spec in CATALOGUE.items():
            if spec.absorbed_by_nominal:
                skipped[name] = "absorbed by the nominal refit: " + spec.absorbed_by_nominal
            elif name == "stribeck_friction" and "coulomb_friction" not in accepted:
                # The Stribeck term is the breakaway peak on top of a Coulomb level; alone it would
                # just be a Coulomb friction that fades at speed.
                skipped[name] = "tested once coulomb_friction is accepted (breakaway on top of Coulomb)"
            elif not all(has[n] for n in spec.needs):
                need = {"v": "a measured velocity column (v=...)", "vbat": "a battery voltage column (vbat=...)",
                        "m": "a payload column (m=...)"}
                skipped[name] = "needs " + " and ".join(need[n] for n in spec.needs)
            else:
                names.append(name)
        return names, skipped


def _mujoco_model(**kw):
    try:
        mod = importlib.import_module("sim_backends.velociroach")
    except ImportError as e:
        raise ModelNotAvailable(
            "model 'velociroach' needs the MuJoCo backend sim_backends.velociroach, which is not available "
            f"yet ({e}); use --model axis for now"
        ) from e
    factory = getattr(mod, "calibration_model", None)
    if factory is None:
        raise ModelNotAvailable(
            "model 'velociroach': sim_backends.velociroach exists but does not expose calibration_model() "
            "(the grey-box adapter for calibration is not written yet); use --model axis for now"
        )
    return factory(**kw)


def _checkpoint_model(**kw):
    raise ModelNotAvailable(
        "model 'checkpoint' (a learned dynamics model as nominal) is not available yet: learning/ does not "
        "expose a loadable dynamics checkpoint with a one-step/rollout API; use --model axis for now"
    )


MODELS = {
    "axis": lambda **kw: AxisModel(**kw),
    "velociroach": _mujoco_model,
    "checkpoint": _checkpoint_model,
}


def get_model(name: str, **kw) -> Model:
    """Instantiate a registered nominal model by name."""
    if name not in MODELS:
        raise UnknownModel(f"unknown model {name!r}; known models: {', '.join(sorted(MODELS))}")
    return MODELS[name](**kw)


def save_model(fitted: FittedAxis, path: str | Path, extra: dict | None = None) -> Path:
    path = Path(path)
    doc = fitted.to_dict()
    if extra:
        doc.update(extra)
    path.write_text(json.dumps(doc, indent=2))
    return path


def load_model(path: str | Path) -> FittedAxis:
    """Load an augmented model written by :func:`run_calibration` (``model.json``)."""
    doc = json.loads(Path(path).read_text())
    if doc.get("model") != "axis":
        raise UnknownModel(f"{path}: model {doc.get('model')!r} cannot be loaded (known: axis)")
    return FittedAxis(axis.AxisParams.from_dict(doc["params"]))
