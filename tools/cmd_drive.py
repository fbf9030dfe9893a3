"""`hil drive`: open-loop driving through the driver contract; `hil find-port`: serial ports.

    hil drive velociroach --backend emulated --action 0.6,0.6 --seconds 3 --json
    hil drive velociroach --backend real --port /dev/ttyUSB0 --action 0.3,0.3 --seconds 2
    hil drive pointmass --backend sim --action 0.5,0 --seconds 2
    hil find-port

Actions are normalized: -1..1 maps onto each action channel's [low, high] from the spec
(for the VelociRoACH: ±max_leg_vel_rps, or ±1 duty in pwm mode). The loop is
read → write → tick at the control period, so it runs unchanged on every backend.
"""

from __future__ import annotations

import math
from typing import Any

import typer

from tools.common import UserError, echo_json, user_errors


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


def drive_run(robot: str, backend: str | None, action: str, seconds: float,
              port: str | None = None) -> dict[str, Any]:
    """Drive open loop; returns the summary printed by `hil drive --json`.

    ``backend`` None: the one the robot config names (``backend:`` in the YAML)."""
    import numpy as np

    from drivers.registry import make_driver

    if not (seconds > 0 and math.isfinite(seconds)):
        raise UserError(f"--seconds must be a positive number, got {seconds}")
    params: dict[str, Any] = {}
    if port:
        params["port"] = port
    drv = make_driver(robot, backend=backend, **params)
    sp = drv.spec
    a_norm = np.array(parse_action(action, sp.action.dim, sp.action.names))
    lo, hi = sp.action.low, sp.action.high
    a = (lo + hi) / 2 + a_norm * (hi - lo) / 2
    n_steps = max(1, round(seconds / sp.period_s))
    with drv:
        first = drv.read()
        start = _pose(sp.state.names, first.state)
        path_m = 0.0
        prev = start
        for _ in range(n_steps):
            obs = drv.read()
            p = _pose(sp.state.names, obs.state)
            if p["x"] is not None and prev["x"] is not None:
                path_m += math.hypot(p["x"] - prev["x"], p["y"] - prev["y"])
            prev = p
            drv.write(a)
            drv.tick()
        drv.stop()
        last = drv.read()
        health = drv.health().to_dict()
    end = _pose(sp.state.names, last.state)
    out: dict[str, Any] = {"robot": sp.name, "backend": drv.backend, "seconds": seconds, "steps": n_steps,
                           "action": a.tolist(), "action_normalized": a_norm.tolist()}
    if start["x"] is not None and end["x"] is not None:
        dx, dy = end["x"] - start["x"], end["y"] - start["y"]
        out["distance_m"] = math.hypot(dx, dy)
        out["path_length_m"] = path_m + math.hypot(end["x"] - prev["x"], end["y"] - prev["y"])
        if start["yaw"] is not None:
            # along the heading at the start: negative means it went backwards
            out["forward_m"] = dx * math.cos(start["yaw"]) + dy * math.sin(start["yaw"])
    out["start_pose"] = start
    out["final_pose"] = end
    out["link"] = health
    return out


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def drive(
        robot: str = typer.Argument(..., help="robot config name or path (configs/robots/), e.g. velociroach"),
        backend: str = typer.Option(None, "--backend",
                                    help="sim | emulated | real (default: the config's backend:)"),
        action: str = typer.Option(..., "--action", help="normalized action per channel in [-1, 1], e.g. 0.6,0.6"),
        seconds: float = typer.Option(3.0, "--seconds", help="how long to drive [s] (sim: simulated seconds)"),
        port: str = typer.Option(None, "--port", help="serial port of the radio (real backend), e.g. /dev/ttyUSB0"),
        json_out: bool = typer.Option(False, "--json", help="print one JSON line"),
    ) -> None:
        """Drive a robot open loop and report distance, final pose and link statistics."""
        if backend is not None and backend not in ("sim", "emulated", "real"):
            raise UserError(f"--backend {backend!r}: expected sim, emulated or real")
        res = drive_run(robot, backend, action, seconds, port=port)
        if json_out:
            echo_json(res)
            return
        fp = res["final_pose"]
        typer.echo(f"{res['robot']} ({res['backend']}): action {res['action']} for {seconds:g} s ({res['steps']} steps)")
        if "distance_m" in res:
            fwd = f", forward {res['forward_m']:+.3f} m" if "forward_m" in res else ""
            typer.echo(f"  distance {res['distance_m']:.3f} m (path {res['path_length_m']:.3f} m){fwd}")
        yaw = "n/a" if fp["yaw"] is None else f"{math.degrees(fp['yaw']):.1f} deg"
        typer.echo(f"  final pose x={fp['x']:.3f} m y={fp['y']:.3f} m yaw={yaw}")
        lk = res["link"]
        lat = "n/a" if lk.get("latency_s") is None else f"{lk['latency_s'] * 1e3:.1f} ms"
        typer.echo(f"  link ok={lk['ok']} quality={lk['link_quality']:.2f} sent={lk['frames_sent']} "
                   f"received={lk['frames_received']} corrupt={lk['corrupt_frames']} "
                   f"dropped={lk['dropped_frames']} latency={lat}")

    @app.command("find-port")
    @user_errors
    def find_port(json_out: bool = typer.Option(False, "--json", help="print one JSON line")) -> None:
        """List serial ports that could be the base-station XBee (USB serial adapters first)."""
        from serial.tools import list_ports

        ports = []
        for p in sorted(list_ports.comports(), key=lambda p: (p.vid is None, p.device)):
            ports.append({
                "device": p.device, "description": p.description, "hwid": p.hwid,
                "manufacturer": p.manufacturer, "serial_number": p.serial_number,
                # FTDI (0403) is what Digi's XBee USB boards use
                "likely_xbee": p.vid == 0x0403 or "xbee" in (p.description or "").lower(),
            })
        if json_out:
            echo_json({"ports": ports})
            return
        if not ports:
            typer.echo("no serial ports found (is the base-station XBee plugged in? "
                       "on Linux, check `dmesg | tail` and membership of the dialout group)")
            return
        for p in ports:
            mark = "  <- XBee?" if p["likely_xbee"] else ""
            typer.echo(f"{p['device']}\t{p['description']}\t{p['hwid']}{mark}")
