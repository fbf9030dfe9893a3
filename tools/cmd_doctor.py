"""`hil doctor RIG`: what a real rig needs from this computer, and what to fix; `hil find-port`:
the USB serial devices, named by vendor and product (tools/doctor.py).

    hil doctor roach_real              # one line per item; exit 0 only when the rig can start
    hil doctor my_arm_rig.yaml --scan  # also ask the devices: Dynamixel IDs, XBee AT settings
    hil find-port --json
"""

from __future__ import annotations

from pathlib import Path

import typer

from hilstack.tools.common import EXIT_RUNTIME, complete_rig, echo_json, user_errors


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def doctor(
        rig: str = typer.Argument(..., help="rig name (configs/rigs) or YAML path", autocompletion=complete_rig),
        scan: bool = typer.Option(False, "--scan", help="open the ports and ask the devices (Dynamixel IDs by a "
                                                        "broadcast ping, XBee AT settings)"),
        json_out: bool = typer.Option(False, "--json", help="print one JSON line"),
    ) -> None:
        """Check a rig's prerequisites (serial ports and permissions, FTDI latency, CAN, rendering, cameras).

        Exit 0: ready. Exit 1: not ready, at least one FAIL line (a device port that does not exist
        included: finding it is the doctor's answer, where `hil up` refuses the same rig with 2).
        Exit 2: the check could not run (an unknown rig, a config that does not load, a bad option)."""
        from hilstack.tools import doctor as doc

        items = doc.check_rig(rig, scan=scan)
        rep = doc.report(items)
        if json_out:
            echo_json(rep)
        else:
            for it in items:
                typer.echo(it.line())
            fails = sum(i.ok is False for i in items)
            typer.echo(f"{rig}: ready" if rep["ok"] else f"{rig}: not ready ({fails} to fix)")
        if not rep["ok"]:
            raise typer.Exit(EXIT_RUNTIME)

    @app.command("find-port")
    @user_errors
    def find_port(json_out: bool = typer.Option(False, "--json", help="print one JSON line")) -> None:
        """List USB serial ports, named by USB vendor:product (XBee base station, U2D2, CAN adapters)."""
        from hilstack.tools import doctor as doc

        ports = doc.serial_ports(Path("/"))
        if json_out:
            echo_json({"ports": ports})
            return
        if not ports:
            typer.echo("no USB serial ports found (is the adapter plugged in? on Linux, check `dmesg | tail` "
                       "and membership of the dialout group)")
            return
        for p in ports:
            name = p["known_as"] or f"unknown: {p['manufacturer'] or '?'} {p['product'] or ''}".rstrip()
            use = doc.ROLE_USE.get(p["role"], "")
            typer.echo(f"{p['device']}\t{p['vid_pid']}\t{name}" + (f"\t<- {use}" if use else ""))
