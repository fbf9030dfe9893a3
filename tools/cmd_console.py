"""hil console: the operator's terminal view of a live rig, with the e-stop keys (tools/console.py)."""

from __future__ import annotations

import sys

import typer

from hilstack.tools.common import EndpointOpt, UserError, complete_rig, rig_bus, user_errors


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def console(
        rig: str = typer.Argument(..., help="rig config (its nodes are up: `hil up RIG`)", autocompletion=complete_rig),
        robots: list[str] = typer.Option(None, "--robot", help="robot to show (repeatable; default: the rig's robots)"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """A terminal console of a live rig: its nodes, each robot's health (ok/stale, stopped
        reason, link counters, rate, deadline overruns), the reset supervisor and the e-stop.

        Keys: e engages the rig's e-stop, r releases it in this bus user's name (the rig's access control applies), q quits.

        The console never commands a robot. Needs the operator extra (textual)."""
        from hilstack.configs.extras import require

        require("textual", "hil console")
        name, bus, cfg = rig_bus(rig, endpoint)
        if robots:
            if cfg is not None and (bad := [r for r in robots if r not in cfg.robots]):
                raise UserError(f"rig {name} has no robot {bad[0]!r} (it has {', '.join(cfg.robots)})")
            shown = list(robots)
        elif cfg is not None:
            shown = list(cfg.robots)
        else:
            raise UserError(f"rig {name} is no rig config: name the robots with --robot")
        if not sys.stdin.isatty():
            raise UserError("hil console is a terminal UI: stdin is not a terminal")
        from hilstack.tools.console import RigWatch, make_app

        watch = RigWatch(name, bus, shown).start()
        try:
            make_app(watch).run()
        finally:
            watch.close()
