"""`hil drive`: open-loop driving through the driver contract.

    hil drive velociroach --backend emulated --action 0.6,0.6 --seconds 3 --json
    hil drive velociroach --backend real --port /dev/ttyUSB0 --action 0.3,0.3 --seconds 2
    hil drive velociroach --backend emulated --action 0.5,0.5 --tlog runs/roach.tlog
    hil drive pointmass --backend sim --action 0.5,0 --seconds 2
    hil drive widowx --backend emulated --seconds 2 --json
    hil drive shadow_hand --backend emulated --seconds 2 --json   # hold the pose, report tracking

Actions are normalized: -1..1 maps onto each action channel's [low, high] from the spec
(for the VelociRoACH: ±max_leg_vel_rps, or ±1 duty in pwm mode). The loop is
read → write → tick at the control period, so it runs unchanged on every backend.
Without --action every channel gets 0.3. Where an action channel is also a state channel
(an arm's joint velocities), the summary reports the tracking error: the RMS of applied
minus measured over the run. Without --json, one line says when the driver is active and
driving (a long run is not silent until its summary).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import typer

from hilstack.tools.common import UserError, complete_robot, echo_json, user_errors


def parse_action(text: str, dim: int, names: tuple[str, ...]) -> list[float]:
    try:
        vals = [float(v) for v in text.replace(" ", "").split(",") if v != ""]
    except ValueError:
        raise UserError(f"--action {text!r}: expected {dim} comma-separated numbers in [-1, 1] "
                        f"for {list(names)}") from None
    if len(vals) != dim:
        raise UserError(f"--action {text!r}: got {len(vals)} value(s), the robot needs {dim} "
                        f"for {list(names)}")
    bad = [v for v in vals if not math.isfinite(v) or abs(v) > 1.0]
    if bad:
        raise UserError(f"--action {text!r}: values must be finite and within [-1, 1] (normalized), got {bad}")
    return vals


def _pose(names: tuple[str, ...], s: Any) -> dict[str, float | None]:
    def get(n: str) -> float | None:
        return float(s[names.index(n)]) if n in names else None

    yaw = get("yaw")
    if yaw is None and "cos_yaw" in names:
        yaw = math.atan2(get("sin_yaw"), get("cos_yaw"))  # type: ignore[arg-type]
    return {"x": get("x"), "y": get("y"), "yaw": yaw}


#: the normalized action on every channel when --action is not given
DEFAULT_ACTION = 0.3


def drive_run(robot: str, backend: str | None, action: str | None, seconds: float, port: str | None = None,
              tlog: str | None = None, on_active: Callable[[Any], None] | None = None) -> dict[str, Any]:
    """Drive open loop; returns the summary printed by `hil drive --json`.

    ``backend`` None: the one the robot config names (``backend:`` in the YAML).
    ``tlog``: append every MAVLink frame of the radio link to this file (real and
    emulated backends of a MAVLink robot; the sim backend has no link).
    ``on_active(driver)``: called once the driver is active and its first reading is in,
    before the first command."""
    import threading

    from hilstack.bus.lifetime import on_stop_signal

    # Ctrl-C/SIGTERM end the drive early: the robot is stopped by the driver and the summary
    # still printed (before: SIGTERM ended the process with the robot moving, left to its
    # device's watchdog); kept also when it comes while the driver loads (bus/lifetime.py)
    asked = threading.Event()
    forget = on_stop_signal(asked.set) if threading.current_thread() is threading.main_thread() else None
    try:
        return _drive(robot, backend, action, seconds, port, tlog, on_active, asked)
    finally:
        if forget is not None:
            forget()


def _drive(robot: str, backend: str | None, action: str | None, seconds: float, port: str | None, tlog: str | None,
           on_active: Callable[[Any], None] | None, asked: Any) -> dict[str, Any]:
    """:func:`drive_run`'s drive; ``asked`` (an Event) set: stop the robot and summarise now."""
    import numpy as np

    from hilstack.drivers.registry import make_driver

    if not (seconds > 0 and math.isfinite(seconds)):
        raise UserError(f"--seconds must be a positive number, got {seconds}")
    params: dict[str, Any] = {}
    if port:
        params["port"] = port
    if tlog:
        params["tlog"] = str(tlog)
    drv = make_driver(robot, backend=backend, **params)
    if tlog and drv.backend == "sim":
        raise UserError(f"--tlog {tlog}: the sim backend has no radio link to log; "
                        "use --backend emulated or real")
    sp = drv.spec
    # without --action: a robot that holds position (no fixed safe action: the hand) holds
    # the command held at activation (the measured state); others drive at DEFAULT_ACTION
    if action is None and sp.safe_action is not None:
        action = ",".join([str(DEFAULT_ACTION)] * sp.action.dim)
    if action is None:
        a = a_norm = None
    else:
        a_norm = np.array(parse_action(action, sp.action.dim, sp.action.names))
        a = sp.action.denormalize(a_norm)
    # action channels that are measured too (joint velocities): tracking error
    tracked = [(i, sp.state.names.index(n)) for i, n in enumerate(sp.action.names) if n in sp.state.names]
    sq_err = np.zeros(len(tracked))
    n_tracked = 0
    applied = None
    n_steps = max(1, round(seconds / sp.period_s))
    with drv:
        first = drv.read()
        if on_active is not None:
            on_active(drv)
        start = _pose(sp.state.names, first.state)
        path_m = 0.0
        prev = start
        done = 0
        for _ in range(n_steps):
            if asked.is_set():
                break
            done += 1
            obs = drv.read()
            p = _pose(sp.state.names, obs.state)
            if p["x"] is not None and prev["x"] is not None:
                path_m += math.hypot(p["x"] - prev["x"], p["y"] - prev["y"])
            prev = p
            if applied is not None and tracked:
                # what was applied during the period that just ended vs what was measured at its end
                sq_err += np.array([(applied[i] - obs.state[j]) ** 2 for i, j in tracked])
                n_tracked += 1
            applied = drv.write(drv.held_command if a is None else a)
            drv.tick()
        last = drv.read()
        # a joint-space robot reports how well it tracked the last command (None: it reports none)
        tracking = drv.tracking_error(last.state, applied)
        drv.stop()
        health = drv.health().to_dict()
    end = _pose(sp.state.names, last.state)
    out: dict[str, Any] = {"robot": sp.name, "backend": drv.backend, "seconds": seconds, "steps": done,
                           "action": applied.tolist(),
                           "action_normalized": None if a_norm is None else a_norm.tolist()}
    if tracking is not None:
        out["tracking_error"] = tracking
    if start["x"] is not None and end["x"] is not None:
        dx, dy = end["x"] - start["x"], end["y"] - start["y"]
        out["distance_m"] = math.hypot(dx, dy)
        out["path_length_m"] = path_m + math.hypot(end["x"] - prev["x"], end["y"] - prev["y"])
        if start["yaw"] is not None:
            # along the heading at the start: negative means it went backwards
            out["forward_m"] = dx * math.cos(start["yaw"]) + dy * math.sin(start["yaw"])
    if n_tracked:
        rms = np.sqrt(sq_err / n_tracked)
        out["tracking_rms"] = {sp.action.names[i]: float(r) for (i, _), r in zip(tracked, rms, strict=True)}
        out["tracking_rms_units"] = {sp.action.names[i]: sp.action.units[i] for i, _ in tracked}
    if start["x"] is not None:
        out["start_pose"] = start
        out["final_pose"] = end
    else:
        out["final_state"] = {n: float(v) for n, v in zip(sp.state.names, last.state, strict=True)}
    out["link"] = health
    if asked.is_set():
        out["stopped_by"] = "signal"  # ended early by Ctrl-C/SIGTERM; the robot was stopped
    if tlog:
        out["tlog"] = str(tlog)
    return out


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def drive(
        robot: str = typer.Argument(..., help="robot config name or path (configs/robots/), e.g. velociroach",
                                   autocompletion=complete_robot),
        backend: str = typer.Option(None, "--backend",
                                    help="sim | emulated | real (default: the config's backend:)"),
        action: str = typer.Option(None, "--action", help="normalized action per channel in [-1, 1], e.g. 0.6,0.6; "
                                   f"omitted: {DEFAULT_ACTION} on every channel, or, for a robot that holds position "
                                   "(the hand), hold the measured state"),
        seconds: float = typer.Option(3.0, "--seconds", help="how long to drive [s] (sim: simulated seconds)"),
        port: str = typer.Option(None, "--port", help="serial port of the radio (real backend), e.g. /dev/ttyUSB0"),
        tlog: str = typer.Option(None, "--tlog", help="append every MAVLink frame to this .tlog "
                                 "(emulated/real backends; read it with `python -m hilstack.drivers.velociroach.mavlink dump`)"),
        json_out: bool = typer.Option(False, "--json", help="print one JSON line"),
    ) -> None:
        """Drive a robot open loop and report distance, final pose and link statistics."""
        if backend is not None and backend not in ("sim", "emulated", "real"):
            raise UserError(f"--backend {backend!r}: expected sim, emulated or real")
        def started(drv: Any) -> None:
            # a long run says at once that it is driving (the summary comes at the end)
            typer.echo(f"{drv.spec.name} ({drv.backend}): driving for {seconds:g} s")  # click flushes

        res = drive_run(robot, backend, action, seconds, port=port, tlog=tlog,
                        on_active=None if json_out else started)
        if json_out:
            echo_json(res)
            return
        act = [round(v, 3) for v in res["action"]]
        typer.echo(f"{res['robot']} ({res['backend']}): action {act} for {seconds:g} s ({res['steps']} steps)")
        if res.get("stopped_by") == "signal":
            typer.echo(f"  stopped early by a stop signal after {res['steps']} steps; the robot was stopped")
        if "tracking_error" in res:
            te = res["tracking_error"]
            typer.echo(f"  joint tracking error: max {te['max_rad']:.4f} rad ({te['worst_joint']}), "
                       f"rms {te['rms_rad']:.4f} rad")
        if "distance_m" in res:
            fwd = f", forward {res['forward_m']:+.3f} m" if "forward_m" in res else ""
            typer.echo(f"  distance {res['distance_m']:.3f} m (path {res['path_length_m']:.3f} m){fwd}")
        if "final_pose" in res:
            fp = res["final_pose"]
            yaw = "n/a" if fp["yaw"] is None else f"{math.degrees(fp['yaw']):.1f} deg"
            typer.echo(f"  final pose x={fp['x']:.3f} m y={fp['y']:.3f} m yaw={yaw}")
        for n, r in res.get("tracking_rms", {}).items():
            typer.echo(f"  tracking rms {n}: {r:.4f} {res['tracking_rms_units'][n]}")
        lk = res["link"]
        lat = "n/a" if lk.get("latency_s") is None else f"{lk['latency_s'] * 1e3:.1f} ms"
        typer.echo(f"  link ok={lk['ok']} quality={lk['link_quality']:.2f} sent={lk['frames_sent']} "
                   f"received={lk['frames_received']} corrupt={lk['corrupt_frames']} "
                   f"dropped={lk['dropped_frames']} latency={lat}")
        if tlog:
            typer.echo(f"  MAVLink log: {tlog}")
