"""hil viz: live rerun view of a rig, or an MCAP recording converted to .rrd."""

from __future__ import annotations

from pathlib import Path

import typer

from hilstack.tools.common import EndpointOpt, UserError, rig_bus, user_errors


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def viz(
        rig: str = typer.Option(None, "--rig", help="rig to subscribe to (live): config name or file, or a rig name"),
        recording: Path = typer.Option(None, "--recording", help="MCAP file to convert instead of live"),
        save: Path = typer.Option(None, "--save", help="write a .rrd file (headless)"),
        spawn: bool = typer.Option(False, "--spawn", help="spawn the rerun viewer"),
        seconds: float = typer.Option(None, "--seconds", help="stop after this long"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """Log a rig's state, commands, plans and images to rerun with a fixed layout.

        Live: `hil viz --rig NAME --spawn` (viewer), `--save out.rrd` (headless), or
        neither (serves gRPC; connect a viewer with `rerun --connect`)."""
        from hilstack.tools.viz import viz_live, viz_recording

        if recording is not None:
            if save is None:
                raise UserError("--recording needs --save OUT.rrd")
            from hilstack.tools.cmd_record import _recording_arg

            _recording_arg(recording)  # not MCAP (empty, CSV...): one line, nothing written
            n = viz_recording(recording, save)
            typer.echo(f"wrote {n} messages to {save}; open with: rerun {save}", err=True)
            return
        if rig is None:
            raise UserError("give --rig NAME (live) or --recording FILE --save OUT.rrd")
        rig, bus, _ = rig_bus(rig, endpoint)
        v = viz_live(rig, bus, seconds=seconds, save=save, spawn=spawn, grpc=not (save or spawn))
        typer.echo(f"logged {v.logged} messages", err=True)
