"""hil up / estop / nodes / calibrate placeholder-free helpers."""

from __future__ import annotations

import subprocess
import sys
import time

import typer

from tools.common import EndpointOpt, UserError, bus_config, echo_json, setup_logging, user_errors


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def up(
        rig: str = typer.Argument(..., help="rig config name or path (configs/rigs/)"),
        robot: str = typer.Option(None, "--robot", help="only this robot of the rig (default: all)"),
        steps: int = typer.Option(None, "--steps", help="stop after this many control periods"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """Bring a rig's robots onto the bus (one driver bridge node per robot)."""
        from configs.schema import load_rig, rig_robot_config
        from drivers.bridge import DriverNode
        from drivers.registry import make_driver

        setup_logging()
        cfg = load_rig(rig)
        bus = bus_config(endpoint) if endpoint else cfg.bus
        names = [robot] if robot else list(cfg.robots)
        for n in names:
            if n not in cfg.robots:
                raise UserError(f"rig {cfg.name} has no robot {n!r}; has {list(cfg.robots)}")
        if len(names) > 1:
            # one process per robot: a slow or failing driver cannot stall another
            procs = []
            for n in names:
                cmd = [sys.executable, "-m", "tools.cli", "up", rig, "--robot", n]
                if steps:
                    cmd += ["--steps", str(steps)]
                if endpoint:
                    cmd += ["--endpoint", endpoint]
                procs.append(subprocess.Popen(cmd))
            try:
                for p in procs:
                    p.wait()
            except KeyboardInterrupt:
                for p in procs:
                    p.terminate()
            # the rig failed if one robot's node did: its exit code (1 link, 2 input) is ours
            failed = [p.returncode for p in procs if p.returncode not in (0, None)]
            if failed:
                raise typer.Exit(1 if 1 in failed else max(failed))
            return
        n = names[0]
        node = DriverNode(
            make_driver(rig_robot_config(cfg, n)),
            cfg.name,
            n,
            bus,
            watchdog_periods=cfg.watchdog_periods,
            pace=cfg.pace,
        )
        typer.echo(f"{n} up on hil/{cfg.name}/{n}/{{state,cmd}} ({node.driver.backend}, {cfg.pace})", err=True)
        try:
            stats = node.serve(max_steps=steps)
        finally:
            node.close()
        typer.echo(f"{n} down: {stats}", err=True)

    @app.command()
    @user_errors
    def estop(
        rig: str = typer.Argument(..., help="rig name"),
        release: bool = typer.Option(False, "--release", help="release a latched e-stop"),
        reason: str = typer.Option("operator", "--reason"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """Engage (latched) or release the rig's e-stop."""
        from bus import keys
        from bus.node import Node
        from bus.schemas import EStop

        node = Node("estop-cli", rig, bus_config(endpoint))
        pub = node.publisher(keys.estop(rig), EStop)
        # repeat briefly so a node that just connected still gets it
        for _ in range(5):
            pub.put(EStop(engaged=not release, reason=reason, source="hil estop"))
            time.sleep(0.02)
        node.close()
        typer.echo(("released" if release else "ENGAGED") + f" e-stop on {rig}", err=True)

    @app.command()
    @user_errors
    def nodes(
        rig: str = typer.Argument(..., help="rig name"),
        json_out: bool = typer.Option(False, "--json"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """List the nodes alive on a rig (liveliness tokens)."""
        from bus.node import Node, alive_nodes

        node = Node("nodes-cli", rig, bus_config(endpoint), handle_signals=False)
        time.sleep(0.3)
        names = [n for n in alive_nodes(node.session, rig) if n != "nodes-cli"]
        node.close()
        if json_out:
            echo_json(names)
        else:
            typer.echo("\n".join(names) if names else "(no nodes)")
