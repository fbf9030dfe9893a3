"""The bounded configuration values: every config schema of the stack, and each safety
parameter's bounds with the physical limit they come from.

    python -m hilstack.tools.config_bounds          # the table of docs/platform.md, "Bounded configuration values"

The bounds live in the schemas (shared types of ``hilstack.configs.schema``: ``PeriodS``,
``StaleS``, ``WatchdogS``..., and each robot's own, made with ``finite()``); this module
only reads them, for the docs, the tests (tests/test_configs.py) and the config fuzzer
(tools/fuzz.py).
"""

from __future__ import annotations

import sys
import types
import typing
from typing import Any

from pydantic import BaseModel
from pydantic.fields import FieldInfo


def config_models(sim: bool = False) -> list[type[BaseModel]]:
    """Every schema of a robot's ``params``, a rig and a reset procedure; with ``sim``
    also the sim backends' ``params.sim`` and the tasks' (not safety values)."""
    from hilstack.configs.schema import BusConfig, EmulatorParams, RigConfig, RigRobot
    from hilstack.control.reset.config import DetectorConfig, ResetConfig, StepConfig, VerifyConfig
    from hilstack.control.reset.steps import STEP_KINDS
    from hilstack.drivers.camera.config import CameraParams
    from hilstack.drivers.dynamixel.params import DynamixelEmulatorParams
    from hilstack.drivers.mocap.driver import MocapParams
    from hilstack.drivers.reset_arm.config import ResetArmParams
    from hilstack.drivers.sawyer.config import SawyerParams
    from hilstack.drivers.shadow_hand.config import HandEmulatorParams, ShadowHandParams
    from hilstack.drivers.velociroach.config import VelociRoachEmulatorParams, VelociRoachParams
    from hilstack.drivers.widowx.config import MechanismParams, WidowXParams
    from hilstack.sim_backends.pointmass import PointMassParams

    out: list[type[BaseModel]] = [
        VelociRoachParams, VelociRoachEmulatorParams, ShadowHandParams, HandEmulatorParams, WidowXParams,
        MechanismParams, DynamixelEmulatorParams, SawyerParams, EmulatorParams, CameraParams, ResetArmParams,
        MocapParams, PointMassParams, RigConfig, RigRobot, BusConfig, ResetConfig, DetectorConfig, StepConfig,
        VerifyConfig]
    out += [k.params_model() for k in STEP_KINDS.values() if k.params_model() not in out]
    out += [m for m in _registered_robot_params() if m not in out]
    if sim:
        from hilstack.learning.baoding import BaodingTaskParams
        from hilstack.sim_backends.shadow_hand.backend import SimParams as HandSimParams
        from hilstack.sim_backends.shadow_hand.cameras import CameraSimParams, TrackerOptions
        from hilstack.sim_backends.velociroach.backend import SimParams as RoachSimParams

        out += [RoachSimParams, HandSimParams, CameraSimParams, TrackerOptions, BaodingTaskParams]
    return out


def _registered_robot_params() -> list[type[BaseModel]]:
    """The params model of every registered robot (a robot added later is checked without an
    edit here): the one its driver class declares (``Driver.params_type``)."""
    from hilstack.drivers.registry import backends_of, resolve, robots

    out = []
    for robot in robots():
        backend = "real" if "real" in backends_of(robot) else "sim"
        model = resolve(robot, backend).params_type
        if isinstance(model, type) and issubclass(model, BaseModel):
            out.append(model)
    return out


def _metadata(annotation: Any, meta: list[Any]) -> list[Any]:
    """The constraints of a field: its own metadata and that of the Annotated types in its
    annotation (``TimeoutS | None``)."""
    out = list(meta)
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        for m in typing.get_args(annotation)[1:]:
            out += m.metadata if isinstance(m, FieldInfo) else [m]
    elif origin in (typing.Union, types.UnionType):
        for a in typing.get_args(annotation):
            out += _metadata(a, [])
    return out


def field_bounds(fi: FieldInfo) -> tuple[tuple[str, float] | None, tuple[str, float] | None, str | None]:
    """``(lower, upper, source)`` of a field: ``("gt", 0.0)``, ``("le", 2.0)`` and what
    physical limit they come from (None where it has none)."""
    from hilstack.configs.schema import Bound

    lo = hi = None
    source = None
    for m in _metadata(fi.annotation, fi.metadata):
        for a in ("gt", "ge"):
            if getattr(m, a, None) is not None:
                lo = (a, float(getattr(m, a)))
        for a in ("lt", "le"):
            if getattr(m, a, None) is not None:
                hi = (a, float(getattr(m, a)))
        if isinstance(m, Bound):
            source = m.source
    return lo, hi, source


def bounds_table() -> str:
    """The markdown table of every bounded safety field: schema, field, range, why (the
    emulators' fault-injection times and pacing, not safety values, are left out)."""
    rows = ["| schema | field | range | why (the physical limit) |", "|---|---|---|---|"]
    sym = {"gt": "(", "ge": "[", "lt": ")", "le": "]"}
    seen: dict[str, str] = {}
    for model in config_models():
        for name, fi in model.model_fields.items():
            lo, hi, source = field_bounds(fi)
            if source is None or lo is None or hi is None or "not a safety value" in source:
                continue
            rng = f"{sym[lo[0]]}{lo[1]:g}, {hi[1]:g}{sym[hi[0]]}"
            key = f"{model.__name__}.{name}"
            if source in seen.values():  # a shared type: say where it was explained
                first = next(k for k, v in seen.items() if v == source)
                why = f"as {first}"
            else:
                why = source
            seen[key] = source
            rows.append(f"| {model.__name__} | `{name}` | {rng} | {why} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    import argparse

    argparse.ArgumentParser(prog="python -m hilstack.tools.config_bounds",
                            description="Print the table of every bounded config value and its source.").parse_args(argv)
    sys.stdout.write(bounds_table() + "\n")


if __name__ == "__main__":
    main()
