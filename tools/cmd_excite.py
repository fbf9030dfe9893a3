"""`hil excite`: drive a rig's robot with a joint-space excitation and record it, the input of
`hil calibrate --model <robot config>` (docs/calibration.md, "The robots' own MuJoCo models").

    hil excite arm_widowx_emulated --out rec.mcap --seconds 80 --effect joint_friction_nm=0.3
    hil calibrate --model configs/robots/widowx.yaml --data rec.mcap --out cal

The rig config names the robot and its backend (emulated: the real driver over a pty to the bus
emulator process, on the wall clock; sim: lockstep). ``--effect KEY=VALUE`` injects what the
emulator's servos carry and the MuJoCo model lacks (joint_friction_nm, joint_damping_nm_s,
input_delay_s: sim_backends/dynamixel/firmware.py EFFECTS), on top of the rig's own
``params.emulator.effects``. The excitation is a random multi-sine per joint (±0.35 rad about a
mid pose, 0.08-0.6 Hz) tracked by joint-velocity commands through the driver contract, which
clamps them to the robot's limits; the recording holds the spec and one RobotState per period
with the action applied during it.
"""

from __future__ import annotations

import math
from pathlib import Path

import typer

from hilstack.tools.common import UserError, echo_json, user_errors


def parse_effects(items: list[str] | None) -> dict[str, float]:
    """``["joint_friction_nm=0.3", ...]`` -> {key: value}; the values are checked by the emulator."""
    out: dict[str, float] = {}
    for it in items or []:
        key, sep, val = it.partition("=")
        if not sep or not key.strip():
            raise UserError(f"--effect {it!r}: expected KEY=VALUE, e.g. joint_friction_nm=0.3")
        try:
            out[key.strip()] = float(val)
        except ValueError:
            raise UserError(f"--effect {it!r}: {val!r} is not a number") from None
    return out


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def excite(
        rig: str = typer.Argument(..., help="rig config name or file (e.g. arm_widowx_emulated)"),
        out: Path = typer.Option(..., "--out", help="MCAP file to write (never overwritten without --force)"),
        robot: str = typer.Option(None, "--robot", help="the rig's robot to excite (default: its first robot)"),
        seconds: float = typer.Option(60.0, "--seconds", help="length of the excitation [s] (wall clock on an "
                                                                "emulated rig)"),
        seed: int = typer.Option(0, "--seed", help="seed of the multi-sine (frequencies, phases, amplitudes)"),
        effect: list[str] = typer.Option(None, "--effect", help="KEY=VALUE the emulator's servos carry "
                                                                "(repeatable; e.g. input_delay_s=0.03)"),
        period_s: float = typer.Option(None, "--period", help="control period [s] (default: the robot config's)"),
        force: bool = typer.Option(False, "--force", help="replace --out if it exists"),
        as_json: bool = typer.Option(False, "--json", help="print a JSON summary"),
    ) -> None:
        """Excite a rig's robot (joint-space multi-sine) and record it to MCAP for `hil calibrate --model`."""
        from hilstack.calibration.robot_rig import record_excitation
        from hilstack.configs.schema import config_path, load_rig, rig_robot_config

        if not (math.isfinite(seconds) and 0 < seconds <= 3600):
            raise UserError(f"--seconds {seconds}: expected a number in (0, 3600]")
        if period_s is not None and not (math.isfinite(period_s) and 0.005 <= period_s <= 0.5):
            raise UserError(f"--period {period_s}: expected a number in [0.005, 0.5] s")
        effects = parse_effects(effect)
        rig_cfg = load_rig(config_path("rigs", rig))
        key = robot or next(iter(rig_cfg.robots))
        if key not in rig_cfg.robots:
            raise UserError(f"--robot {key!r}: rig {rig_cfg.name} has robots {list(rig_cfg.robots)}")
        cfg = rig_robot_config(rig_cfg, key)
        if cfg.backend not in ("sim", "emulated"):
            raise UserError(f"rig {rig_cfg.name}: robot {key!r} is on the {cfg.backend} backend; `hil excite` "
                            "injects effects into an emulated or simulated bench only")
        if out.exists() and not force:
            raise UserError(f"--out {out} exists: not overwritten (choose another file, or --force to replace it)")
        typer.echo(f"exciting {key} ({cfg.robot}, {cfg.backend}) on rig {rig_cfg.name} for {seconds:g} s, "
                   f"effects {effects or 'none'} -> {out}", err=True)

        def progress(k: int, steps: int) -> None:
            if k and k % 500 == 0:
                typer.echo(f"  {k}/{steps} periods", err=True)

        try:
            record_excitation(out, duration_s=seconds, seed=seed, robot=cfg, effects=effects, period_s=period_s,
                              rig=rig_cfg.name, overwrite=force, progress=progress)
        except ValueError as e:  # bad effects (the emulator's one-line check), a robot without joint actions
            raise UserError(str(e).splitlines()[0]) from None
        summary = {"out": str(out), "rig": rig_cfg.name, "robot": key, "backend": cfg.backend,
                   "effects": effects, "seconds": seconds, "seed": seed}
        if as_json:
            echo_json(summary)
        else:
            typer.echo(f"wrote {out}; next: hil calibrate --model {cfg.source or cfg.robot} --data {out} --out DIR")
