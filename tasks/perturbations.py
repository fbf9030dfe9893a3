"""Typed perturbation settings for the VelociRoACH sim, and their presets.

A *condition* (:class:`PerturbationSettings`) is what the thesis' adaptation experiments
change on the robot (ch. 5, real VelociRoACH): a disabled leg, a slope, a miscalibrated
pose, a payload. The sim backend applies one at any time, mid-episode included
(``VelociRoachSim.apply_perturbations``). A terrain changes contact physics, the ground mesh
and its look, so it takes effect at the next reset (per episode; default: the sim's
``params.sim.terrain``), never mid-episode.

Presets live in ``configs/perturbations/<name>.yaml`` (:class:`PerturbationPresets`,
loaded by name with :func:`load_presets`): the training terrains and the training range of
each perturbation (meta-training samples conditions from it), the held-out test conditions
and terrain, and the switching scenario. Unknown keys are errors naming file and field.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from hilstack.configs.schema import Params, config_path, load_yaml_model

#: the robot's six legs (the sim model checks its legs are these: sim_backends/velociroach/model.py)
Leg = Literal["lf", "lm", "la", "rf", "rm", "ra"]
LEG_NAMES: tuple[str, ...] = Leg.__args__
Terrain = Literal["carpet", "styrofoam", "gravel", "turf"]


class PerturbationSettings(Params):
    """One condition of the robot. Every field's default is "not perturbed"."""

    missing_leg: list[Leg] = Field(default_factory=list, description="disabled legs (no ground contact)")
    payload_kg: float = Field(0.0, ge=0, le=0.5, description="towed payload [kg]")
    slope_deg: float = Field(0.0, ge=-30, le=30, description="ground slope, + uphill along world +x")
    heading_offset_deg: float = Field(0.0, ge=-180, le=180, description="reported minus true heading (pose miscalibration)")
    mocap_offset_m: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="reported minus true position [m]")
    terrain: Terrain | None = Field(None, description="the ground from the next reset on (None: the sim's own)")

    def as_backend(self) -> dict[str, Any]:
        """``name → value`` for ``VelociRoachSim.set_perturbation`` (every perturbation, unset = none)."""
        return {"missing_leg": list(self.missing_leg) or None, "payload_kg": self.payload_kg,
                "slope_deg": self.slope_deg, "heading_offset_deg": self.heading_offset_deg,
                "mocap_offset_m": np.asarray(self.mocap_offset_m, dtype=float), "terrain": self.terrain}


class TrainingRange(Params):
    """The conditions meta-training samples from (uniform within each range)."""

    missing_leg: list[Leg] = Field(default_factory=list, description="one of these legs (or none) is disabled")
    missing_leg_probability: float = Field(0.0, ge=0, le=1)
    payload_kg: tuple[float, float] = (0.0, 0.0)
    slope_deg: tuple[float, float] = (0.0, 0.0)
    heading_offset_deg: tuple[float, float] = (0.0, 0.0)

    @model_validator(mode="after")
    def _ordered(self) -> TrainingRange:
        for f in ("payload_kg", "slope_deg", "heading_offset_deg"):
            lo, hi = getattr(self, f)
            if lo > hi:
                raise ValueError(f"{f}: low {lo} > high {hi}")
        return self

    def sample(self, rng: np.random.Generator) -> PerturbationSettings:
        leg = []
        if self.missing_leg and rng.random() < self.missing_leg_probability:
            leg = [self.missing_leg[int(rng.integers(len(self.missing_leg)))]]
        return PerturbationSettings(missing_leg=leg, payload_kg=float(rng.uniform(*self.payload_kg)),
                                    slope_deg=float(rng.uniform(*self.slope_deg)),
                                    heading_offset_deg=float(rng.uniform(*self.heading_offset_deg)))


class Switching(Params):
    """Non-stationary scenario: the conditions in turn, each for ``every_steps`` control steps."""

    every_steps: int = Field(500, ge=1)
    conditions: list[str] = Field(default_factory=lambda: ["normal", "missing_leg"], min_length=2)
    segments: int = Field(6, ge=2)


class PerturbationPresets(Params):
    """``configs/perturbations/<name>.yaml``."""

    RECORDS_SOURCE: ClassVar[bool] = True  # parse_model fills ``source`` with the file path
    source: str | None = None
    training_terrains: list[Terrain] = Field(min_length=1)
    heldout_terrain: Terrain
    training: TrainingRange = TrainingRange()
    #: the test conditions, by name (the report's perturbation names); a name may also be
    #: ``terrain:<preset>`` for the held-out terrain without other perturbations
    tests: dict[str, PerturbationSettings]
    switching: Switching = Switching()

    @model_validator(mode="after")
    def _heldout(self) -> PerturbationPresets:
        if self.heldout_terrain in self.training_terrains:
            raise ValueError(f"heldout_terrain {self.heldout_terrain!r} is also a training terrain")
        unknown = [c for c in self.switching.conditions if c != "normal" and c not in self.tests]
        if unknown:
            raise ValueError(f"switching.conditions: {unknown} are not in tests {sorted(self.tests)} (or 'normal')")
        return self

    def condition(self, name: str) -> PerturbationSettings:
        """A test condition by name; ``normal`` is no perturbation."""
        return PerturbationSettings() if name == "normal" else self.tests[name]


def load_presets(name_or_path: str | Path = "velociroach") -> PerturbationPresets:
    """Presets by name (``configs/perturbations/<name>.yaml``) or path; ConfigError names file and field."""
    return load_yaml_model(config_path("perturbations", name_or_path), PerturbationPresets)
