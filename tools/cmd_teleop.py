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
        device: str = typer.Argument(None, metavar="DEVICE", help="with --gamepad: the gamepad's input device "
                                     "(/dev/input/eventN); default: the first gamepad found"),
        robot: str = typer.Option(None, "--robot", help="robot key in the rig (default: the rig's first)"),
        record: Path = typer.Option(None, "--record", dir_okay=False,
                                    help="also record the rig's bus to this MCAP file (demonstration data)"),
        force: bool = typer.Option(False, "--force", help="with --record: overwrite an existing file"),
        step: float = typer.Option(0.25, "--step", help="drive: speed/turn change per key press, fraction of the "
                                   "range (0, 1]; jog of a position joint: its step"),
        jog_periods: int = typer.Option(5, "--jog-periods", help="jog of a velocity joint: control periods per press"),
        timeout_s: float = typer.Option(20.0, "--timeout-s", help="how long to wait for the robot's spec [s]"),
        gamepad: bool = typer.Option(False, "--gamepad", help="drive with a gamepad (evdev; the keyboard still "
                                     "works when stdin is a terminal): `hil teleop RIG --gamepad [DEVICE]`"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """Drive a robot from the keyboard, through the bus and the driver contract.

        Roach (drive): w/s or up/down speed, a/d or left/right turn. Arms (jog): 1-9 select a
        joint, +/- jog it. Space stops, e engages the rig's e-stop (release: `hil estop RIG
        --release`), q or Ctrl-C quits (stopping the robot). Commands are sent in this bus
        user's name: the rig's access control applies. A live status line shows the command and
        the robot's pose or joint.

        Gamepad (--gamepad, the operator extra): left stick = speed/turn or the selected joint's
        jog, proportional, the stop when released (dead man); D-pad or shoulder buttons select
        the joint; A stop, B e-stop, Select quit. A gamepad that is lost stops the robot (exit 1)."""
        import threading

        from hilstack.bus.lifetime import on_stop_signal

        # Ctrl-C/SIGTERM from here on are kept (bus/lifetime.py), not a traceback while this
        # loads: the teleop node then starts stopped and its wait for the spec ends at once
        forget = on_stop_signal(lambda: None) if threading.current_thread() is threading.main_thread() else None
        try:
            _teleop(rig, device, robot, record, force, step, jog_periods, timeout_s, gamepad, endpoint)
        finally:
            if forget is not None:
                forget()


def _teleop(rig: str, device: str | None, robot: str | None, record: Path | None, force: bool, step: float,
            jog_periods: int, timeout_s: float, gamepad: bool, endpoint: str | None) -> None:
    """`hil teleop`'s body (stop signals are caught by the caller)."""
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
    if device is not None and not gamepad:
        raise UserError(f"{device}: a DEVICE is the gamepad's, with --gamepad (hil teleop RIG --gamepad [DEVICE])")
    tty = sys.stdin.isatty()
    if not tty and not gamepad:
        raise UserError("hil teleop reads the keyboard: stdin is not a terminal (or drive with --gamepad)")
    pad_dev = None
    if gamepad:  # before anything opens: no gamepad is a one-line error, exit 2
        from hilstack.tools.gamepad import NoGamepad, open_gamepad

        try:
            pad_dev = open_gamepad(device)
        except NoGamepad as e:
            raise UserError(str(e)) from None

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
    lost: Exception | None = None
    try:
        with ControllerNode(name, robot, bus, name="teleop", state_timeout_s=1.0) as ctl:
            typer.echo(f"teleop: waiting up to {timeout_s:g} s for {robot}'s spec on rig {name} "
                       f"(is `hil up {rig}` running? Ctrl-C quits)", err=True)
            try:
                # Ctrl-C/SIGTERM end this wait at once (StopRequested: one line, exit 0)
                spec = ctl.wait_ready(timeout_s).to_dict()  # the spec as published on the bus
            except TimeoutError as e:
                typer.echo(f"error: {e}", err=True)
                raise typer.Exit(1) from None
            mapper = TeleopMapper(spec, step=step, jog_periods=jog_periods)
            pad = None
            if pad_dev is not None:
                from hilstack.tools.gamepad import PAD_HELP, Gamepad, GamepadLost

                pad = Gamepad(pad_dev, mapper)
            names = list(spec["state"]["names"])
            help_ = HELP[mapper.mode] if tty else ""
            if pad is not None:
                help_ = f"gamepad {pad.label}: {PAD_HELP[mapper.mode]}" + (f"; keys: {help_}" if help_ else "")
            out.write(f"teleop {robot} on rig {name} as {ctl.user}: {help_}\n")
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
            with KeyReader() if tty else _NoKeys() as keys:
                try:
                    quit_ = False
                    while not quit_ and not ctl.stop_event.is_set():
                        events: list[Event | None] = [mapper.key(k) for k in keys.read(0.0)]
                        if pad is not None:
                            try:
                                events += pad.poll()
                            except GamepadLost as e:
                                lost = e  # the finally below sends the stop; then exit 1
                                break
                        for ev in events:
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
        if pad_dev is not None:
            pad_dev.close()
        if rec is not None:
            rec.stop_event.set()
            rec_thread.join(timeout=5.0)
            rec.close()
            typer.echo(f"recorded to {record}", err=True)
    if lost is not None:
        from hilstack.drivers.base import LinkError

        raise LinkError(str(lost))


class _NoKeys:
    """No keyboard (stdin is no terminal: a gamepad-only teleop)."""

    def __enter__(self) -> _NoKeys:
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def read(self, timeout_s: float = 0.0) -> list[str]:  # noqa: ARG002 - KeyReader's signature
        return []
