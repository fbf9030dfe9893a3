"""hil demo: the README's main job."""

from __future__ import annotations

from pathlib import Path

import typer

from tools.common import UserError, user_errors


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def demo(
        what: str = typer.Argument("roach", help="roach (MBRL) | transfer (SIDM, GAT/GARAT: docs/transfer.md)"),
        out: Path = typer.Option(Path("out/demo"), "--out", help="output directory"),
        quick: bool = typer.Option(False, "--quick", help="smaller run (< 10 min on 2 cores)"),
        seed: int = typer.Option(0, "--seed"),
        planner: str = typer.Option("cem", "--planner", help="cem | random_shooting | pddm"),
        rig: str = typer.Option("roach_sim", "--rig", help="rig config: roach_sim (lockstep), roach_emulated, roach_real"),
        operator_resets: bool = typer.Option(False, "--operator-resets",
                                             help="real rigs: prompt an operator to place the robot"),
    ) -> None:
        """MBRL on the simulated VelociRoACH with every node on the bus; writes a report.

        Collects random data through the driver bridge, trains a dynamics model, runs MPC
        and the differential-drive baseline on five paths at a low and a high speed.
        `hil demo transfer` runs SIDM and GAT/GARAT instead (tools/demo_transfer.py)."""
        if what == "transfer":
            from tools.demo_transfer import cli_transfer

            return cli_transfer(out, quick=quick, seed=seed)
        if what != "roach":
            raise UserError(f"hil demo: unknown demo {what!r} (roach | transfer)")
        from learning.mbrl import RigError
        from tools.demo import run_demo

        try:
            r = run_demo(out, quick=quick, seed=seed, planner=planner, rig=rig, operator_resets=operator_resets)
        except RigError as e:
            typer.echo(f"error: {e}", err=True)
            raise typer.Exit(1) from None
        for s in ("low_speed", "high_speed"):
            if s in r:
                typer.echo(f"{s}: mpc_cost {r[s]['mpc_cost']:.1f}  differential_drive_cost "
                           f"{r[s]['differential_drive_cost']:.1f}")
        typer.echo(f"report: {out / 'report.md'}")
