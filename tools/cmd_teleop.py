"""hil teleop: drive a rig's robot from the keyboard over the bus (tools/teleop.py)."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import typer

from hilstack.tools.common import EndpointOpt, UserError, complete_rig, one_line, rig_bus, user_errors

#: status line refreshes per second (the terminal is not flooded at a fast lockstep sim's rate)
STATUS_HZ = 10.0


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def teleop(
        rig: str = typer.Argument(..., help="rig config (its driver node must be up: `hil up RIG`)", autocompletion=complete_rig),
        robot: str = typer.Option(None, "--robot", help="robot key in the rig (default: the rig's first)"),
        record: Path = typer.Option(None, "--record", dir_okay=False,
                                    help="also record the rig's bus to this MCAP file (demonstration data)"),
        force: bool = typer.Option(False, "--force", help="with --record: overwrite an existing file"),
        step: float = typer.Option(0.25, "--step", help="drive: speed/turn change per key press, fraction of the "
                                   "range (0, 1]; jog of a position joint: its step"),
        jog_periods: int = typer.Option(5, "--jog-periods", help="jog of a velocity joint: control periods per press"),
        timeout_s: float = typer.Option(20.0, "--timeout-s", help="how long to wait for the robot's spec [s]"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """Drive a robot from the keyboard, through the bus and the driver contract.

        Roach (drive): w/s or up/down speed, a/d or left/right turn. Arms (jog): 1-9 select a
        joint, +/- jog it. Space stops, e engages the rig's e-stop (release: `hil estop RIG
        --release`), q or Ctrl-C quits (stopping the robot). Commands are sent in this bus
        user's name: the rig's access control applies. A live status line shows the command and
        the robot's pose or joint."""
        from hilstack.bus.cycle import CycleTimer
        from hilstack.bus.estop import command_estop
        from hilstack.control.controller_node import ControllerNode
        from hilstack.tools.teleop import HELP, Event, KeyReader, TeleopMapper, status_line

        if not (0 < step <= 1):
            raise UserError(f"--step {step}: expected a number in (0, 1]")
        if not (1 <= jog_periods <= 1000):
            raise UserError(f"--jog-periods {jog_periods}: expected an integer in [1, 1000]")
        if not (0 < timeout_s <= 600):
            raise UserError(f"--timeout-s {timeout_s}: expected a number in (0, 600]")
        name, bus, cfg = rig_bus(rig, endpoint)
        if robot is None:
            if cfg is None:
                raise UserError(f"rig {name} is no rig config: name the robot with --robot")
            robot = next(iter(cfg.robots))
        elif cfg is not None and robot not in cfg.robots:
            raise UserError(f"rig {name} has no robot {robot!r} (it has {', '.join(cfg.robots)})")
        if bus.access is not None:
            from hilstack.bus.access import user_of

            user = user_of(bus.access)
            if user not in bus.access.command:
                raise UserError(f"user {user!r} may not command rig {name} (bus.access.command: "
                                f"{bus.access.command})")
        if not sys.stdin.isatty():
            raise UserError("hil teleop reads the keyboard: stdin is not a terminal")

        rec = rec_thread = None
        if record is not None:
            from hilstack.bus.recording import Recorder

            try:
                rec = Recorder(name, record, bus, overwrite=force, handle_signals=False)
            except (ValueError, OSError) as e:
                raise UserError(f"--record {record}: {one_line(e)}") from None
            rec_thread = threading.Thread(target=rec.record, name="teleop-record", daemon=True)
            rec_thread.start()

        out = sys.stdout
        try:
            with ControllerNode(name, robot, bus, name="teleop", state_timeout_s=1.0) as ctl:
                try:
                    spec = ctl.wait_ready(timeout_s).to_dict()  # the spec as published on the bus
                except TimeoutError as e:
                    typer.echo(f"error: {e}", err=True)
                    raise typer.Exit(1) from None
                mapper = TeleopMapper(spec, step=step, jog_periods=jog_periods)
                names = list(spec["state"]["names"])
                out.write(f"teleop {robot} on rig {name} as {ctl.user}: {HELP[mapper.mode]}\n")
                out.flush()
                state = None
                estop = ""
                last_seq = -1
                state_t = time.monotonic()
                next_draw = 0.0
                # one command per control period of wall clock, on every pace: a lockstep sim
                # then runs in real time for the operator instead of as fast as the CPU goes
                timer = CycleTimer(float(spec["period_s"]), sleep=ctl.stop_event.wait)
                timer.start()
                with KeyReader() as keys:
                    try:
                        quit_ = False
                        while not quit_ and not ctl.stop_event.is_set():
                            for k in keys.read(0.0):
                                ev: Event | None = mapper.key(k)
                                if ev is not None and ev.kind == "quit":
                                    quit_ = True
                                elif ev is not None and ev.kind == "estop":
                                    res = command_estop(ctl, engaged=True, reason="teleop", timeout_s=2.0)
                                    estop = ("E-STOP ENGAGED (release: hil estop --release)" if res.ok
                                             else "E-STOP sent, NOT acknowledged by every driver")
                            if quit_:
                                break
                            try:
                                state = ctl.next_state(after_seq=last_seq, timeout_s=0.2)
                            except TimeoutError:
                                pass  # no new state: keep reading keys (q still quits)
                            else:
                                last_seq = state.seq
                                state_t = time.monotonic()
                                ctl.send_action(mapper.action(list(state.action)), state.seq)
                            now = time.monotonic()
                            if now >= next_draw:
                                next_draw = now + 1.0 / STATUS_HZ
                                line = status_line(robot, mapper, state, names, estop, now - state_t)
                                out.write("\r" + line + "\x1b[K")
                                out.flush()
                            timer.wait()
                    except KeyboardInterrupt:
                        pass
                    finally:
                        # leave the robot stopped: the safe action for the newest state
                        mapper.stop()
                        if state is not None:
                            ctl.send_action(mapper.action(list(state.action)), state.seq)
                        out.write("\n")
                        out.flush()
        finally:
            if rec is not None:
                rec.stop_event.set()
                rec_thread.join(timeout=5.0)
                rec.close()
                typer.echo(f"recorded to {record}", err=True)
