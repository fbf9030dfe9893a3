"""hil record / replay / inspect / foxglove."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import typer

from hilstack.tools.common import (
    EndpointOpt,
    UserError,
    bus_config,
    echo_json,
    rig_bus,
    user_errors,
)

#: `hil record` warns when no node is alive on the rig this long after it started [s]
NO_NODE_WARN_S = 3.0


def _recording_arg(path: Path) -> None:
    """A one-line exit-2 error unless ``path`` is an MCAP recording (empty file, CSV, random
    bytes...); also used by `hil viz --recording`."""
    from hilstack.bus.recording import NotARecording, check_mcap

    try:
        check_mcap(path)
    except NotARecording as e:
        raise UserError(str(e)) from None


def _out_error(out: Path, e: OSError) -> UserError:
    from hilstack.bus.recording import RecordingExists

    if isinstance(e, RecordingExists):
        return UserError(f"--out {out} exists: not overwritten (choose another file, or --force to replace it)")
    return UserError(f"--out {out}: cannot write it ({e.strerror or e})")


def _default_out(rig: str) -> Path:
    """recordings/<rig>-<time>.mcap, with -2, -3... when that name is taken (never overwritten)."""
    base = Path("recordings") / f"{rig}-{time.strftime('%Y%m%d-%H%M%S')}"
    out, k = base.with_suffix(".mcap"), 1
    while out.exists():
        k += 1
        out = base.parent / f"{base.name}-{k}.mcap"
    return out


def _warn_if_no_node(rec, rig: str, wait_s: float) -> None:  # noqa: ANN001 - a Recorder
    """In the background: a warning when no other node is alive on the rig after ``wait_s``."""
    from hilstack.bus.node import alive_nodes

    def check() -> None:
        try:
            seen = [n for n in alive_nodes(rec.session, rig, timeout_s=0.5, window_s=wait_s) if n != rec.name]
        except Exception:  # noqa: BLE001 - the recorder stopped meanwhile: nothing to say
            return
        if not seen and not rec.stop_event.is_set():
            typer.echo(f"warning: no node alive on rig {rig} after {wait_s:g} s (is it up? `hil up {rig}`); "
                       "recording on", err=True)

    threading.Thread(target=check, daemon=True, name="rig-alive-check").start()


RigOpt = typer.Option(..., "--rig", help="rig config name or file (its bus settings are used), or a rig name "
                                          "(key prefix hil/<rig>/)")


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def record(
        rig: str = RigOpt,
        out: Path = typer.Option(None, "--out", help="MCAP file (default recordings/<rig>-<time>.mcap)"),
        seconds: float = typer.Option(None, "--seconds", help="stop after this long (default: until Ctrl-C)"),
        topics: list[str] = typer.Option(
            None, "--topics", help="only topics matching these key expressions (e.g. 'hil/lab/*/state'; the "
                                   "robots' specs are always recorded); repeatable. Default: everything of the rig"
        ),
        force: bool = typer.Option(False, "--force", help="replace --out if it exists (default: refuse)"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """Record every message of a rig to one MCAP file (a crash loses at most the last 0.5 s).

        An existing --out is never overwritten without --force."""
        from hilstack.bus.recording import Recorder

        if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
            raise UserError(f"--seconds {seconds}: expected a finite number > 0")
        # a mistyped name: "no such rig config; known: [...]", exit 2 (a recording of nothing is no recording)
        name, bus, _ = rig_bus(rig, endpoint, need_config=True)
        out = out or _default_out(name)
        try:
            rec = Recorder(name, out, bus, topics=topics, overwrite=force, join_wait_s=5.0)  # --seconds count once joined
        except ValueError as e:
            raise UserError(str(e)) from None
        except OSError as e:
            raise _out_error(out, e) from None
        what = " ".join(topics) + " (and the specs)" if topics else f"hil/{name}/**"
        typer.echo(f"recording {what} to {out} (Ctrl-C to stop)", err=True)
        _warn_if_no_node(rec, name, NO_NODE_WARN_S)
        try:
            n = rec.record(seconds)
        finally:
            rec.close()
        left = f", {rec.filtered} left out by --topics" if topics else ""
        typer.echo(f"wrote {n} messages to {out} ({rec.malformed} malformed payloads skipped{left})", err=True)

    @app.command()
    @user_errors
    def foxglove(
        rig: str = RigOpt,
        host: str = typer.Option("127.0.0.1", "--host", help="address to serve on (0.0.0.0: every interface)"),
        port: int = typer.Option(8765, "--port", help="WebSocket port (Foxglove's default is 8765)"),
        seconds: float = typer.Option(None, "--seconds", help="stop after this long (default: until Ctrl-C)"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """Live view of a rig in Foxglove (WebSocket server; robots in the 3D panel).

        Foxglove's panels may publish teleop commands on hil/<rig>/<robot>/cmd and an e-stop
        engage on hil/<rig>/estop, in this bus user's name (the rig's access control applies)."""
        from hilstack.tools.foxglove_live import FoxgloveLive

        if not 0 <= port <= 65535:
            raise UserError(f"--port {port}: expected 0..65535")
        rig, bus, _ = rig_bus(rig, endpoint)
        try:
            live = FoxgloveLive(rig, bus, host=host, port=port)
        except RuntimeError as e:
            raise UserError(str(e)) from None
        typer.echo(f"serving hil/{rig}/** to Foxglove at {live.url} "
                   "(Foxglove: Open connection -> Foxglove WebSocket; Ctrl-C to stop)", err=True)
        n = live.serve(seconds)
        typer.echo(f"forwarded {n} messages ({live.malformed} malformed payloads skipped); from clients: "
                   f"{live.client_commands} commands, {live.client_estops} e-stop engages, "
                   f"{len(live.refused)} refused", err=True)

    @app.command()
    @user_errors
    def replay(
        path: Path = typer.Argument(..., exists=True, dir_okay=False, help="MCAP recording"),
        speed: float = typer.Option(1.0, "--speed", help="playback speed factor; 0 = as fast as possible"),
        rig: str = typer.Option(None, "--rig", help="publish under hil/<rig>/ instead of the recorded rig: a rig "
                                                    "config name or file (its bus settings are used), or a name"),
        topics: list[str] = typer.Option(
            None, "--topics", help="only recorded topics matching these key expressions (e.g. 'hil/*/pm/state'); repeatable"
        ),
        include_commands: bool = typer.Option(
            False, "--include-commands", help="also publish commands, e-stop engages, resets, plans and model "
                                              "updates (e-stop releases are never replayed)"
        ),
        force: bool = typer.Option(False, "--force", help="replay even onto a rig with live driver nodes"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """Play a recording back onto the bus (sensor and state topics only, unless --include-commands).

        Refuses when the target rig has live driver nodes, unless --force.
        """
        from hilstack.bus.recording import ReplayRefused, topic_filter
        from hilstack.bus.recording import replay as do_replay

        if not (math.isfinite(speed) and speed >= 0):
            raise UserError(f"--speed {speed}: expected a finite number >= 0 (0: as fast as possible)")
        _recording_arg(path)
        try:
            topic_filter(topics)
        except ValueError as e:
            raise UserError(f"--topics: {e}") from None
        if rig is not None:
            rig, bus, _ = rig_bus(rig, endpoint)
        else:  # the recorded rig: its config's bus settings when this checkout has it
            from hilstack.bus.recording import recorded_rig

            name = recorded_rig(path)
            bus = rig_bus(name, endpoint)[1] if name else bus_config(endpoint)
        try:
            st = do_replay(
                path, bus, speed=speed, rig=rig, topics=topics,
                include_commands=include_commands, force=force,
            )
        except ReplayRefused as e:
            raise UserError(str(e)) from None
        typer.echo(f"replayed {st.published} messages from {path}", err=True)
        if st.skipped_commands:
            n = sum(st.skipped_commands.values())
            typer.echo(
                f"  not replayed: {n} command messages on {', '.join(sorted(st.skipped_commands))} "
                "(--include-commands to replay them)",
                err=True,
            )
        if st.skipped_releases:
            n = sum(st.skipped_releases.values())
            typer.echo(f"  never replayed: {n} e-stop releases on {', '.join(sorted(st.skipped_releases))} "
                       "(a replay never releases an e-stop)", err=True)
        if st.skipped_by_filter:
            typer.echo(f"  left out by --topics: {st.skipped_by_filter} messages", err=True)

    @app.command()
    @user_errors
    def repair(
        path: Path = typer.Argument(..., exists=True, dir_okay=False, help="MCAP recording, e.g. cut by a crash"),
        out: Path = typer.Option(..., "--out", help="the repaired copy (a new file)"),
        force: bool = typer.Option(False, "--force", help="replace --out if it exists (default: refuse)"),
    ) -> None:
        """Copy a crashed recording into a finished MCAP file that every tool opens.

        A file that is not MCAP is refused (nothing written); an existing --out is never
        overwritten without --force."""
        from hilstack.bus.recording import repair as do_repair

        if out.exists() and out.resolve() == path.resolve():
            raise UserError(f"--out {out} is the recording itself; write the repaired copy to another file")
        _recording_arg(path)
        try:
            r = do_repair(path, out, overwrite=force)
        except OSError as e:
            raise _out_error(out, e) from None
        cut = f"; the source was cut ({r.error}): everything before the damage was kept" if r.truncated else ""
        typer.echo(f"wrote {r.messages} messages on {r.channels} channels to {out}{cut}", err=True)

    @app.command()
    @user_errors
    def inspect(
        path: Path = typer.Argument(..., exists=True, dir_okay=False, help="MCAP recording"),
        json_out: bool = typer.Option(False, "--json", help="one JSON object on stdout"),
    ) -> None:
        """Summarise a recording: channels, counts, rates, gaps."""
        from hilstack.bus.recording import summarize

        _recording_arg(path)
        s = summarize(path)
        if json_out:
            echo_json(s)
            return
        typer.echo(f"{s['path']}: {s['messages']} messages over {s['duration_s']:.2f} s")
        if s["truncated"]:
            typer.echo(f"  warning: file is truncated ({s['error']}); messages up to the damage are shown")
        if s["undecodable"]:
            typer.echo(f"  warning: {s['undecodable']} message(s) did not decode and were skipped "
                       f"(first: {s['undecodable_error']})")
        typer.echo(f"  {'channel':40s} {'type':22s} {'count':>7s} {'rate_hz':>8s} {'max_gap_s':>9s} gaps")
        for topic, c in s["channels"].items():
            typer.echo(
                f"  {topic:40s} {c['type']:22s} {c['count']:7d} {c['rate_hz']:8.1f} {c['max_gap_s']:9.3f} {c['gaps']}"
            )
        for topic, c in s["other_channels"].items():
            typer.echo(f"  {topic:40s} {c['schema']:22s} {c['count']:7d}  (derived, not replayed)")
