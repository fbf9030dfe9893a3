"""hil adapt: the online-adaptation node (learns from a rig's state stream, feeds `hil mpc --adapt`)."""

from __future__ import annotations

from pathlib import Path

import typer

from hilstack.tools.common import EndpointOpt, UserError, complete_rig, echo_json, rig_bus, user_errors


def send_names(send: str, adapter) -> list[str] | None:
    """``--send``: ``all`` (None), ``last_layer`` or comma-separated parameter names."""
    from hilstack.learning.adaptation.node import last_layer

    if send == "all":
        return None
    if send == "last_layer":
        return last_layer(adapter)
    names = [n.strip() for n in send.split(",") if n.strip()]
    unknown = sorted(set(names) - set(adapter.theta_star))
    if not names or unknown:
        raise UserError(f"--send {send!r}: expected all, last_layer or parameter names of the model "
                        f"({', '.join(sorted(adapter.theta_star))})")
    return names


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def adapt(
        rig: str = typer.Argument(..., help="rig config (its driver node must be up: `hil up RIG`)", autocompletion=complete_rig),
        checkpoint: Path = typer.Option(..., "--checkpoint", exists=True, dir_okay=False,
                                        help="adaptation checkpoint (learning/adaptation; the MPC loads the same)"),
        method: str = typer.Option(None, "--method", help="override the checkpoint's method: mb | mb_de | grbal | "
                                                          "rebal | mole"),
        send: str = typer.Option("all", "--send", help="all | last_layer | comma-separated parameter names "
                                                       "(docs/adaptation.md, On the bus)"),
        robot: str = typer.Option(None, "--robot", help="robot key in the rig (default: the only one)"),
        max_updates: int = typer.Option(None, "--max-updates", help="exit after this many updates"),
        idle_timeout_s: float = typer.Option(None, "--idle-timeout", help="exit after this long without a state [s]"),
        json_out: bool = typer.Option(False, "--json"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """Online adaptation on the bus: adapts the model from the robot's last M transitions at
        every control step and publishes it on hil/<rig>/model/update (`hil mpc --adapt` swaps
        it in between plans). Runs until Ctrl-C; prints what it learned from and what it skipped."""
        from hilstack.learning.adaptation import load_adapter
        from hilstack.learning.adaptation.node import AdaptationNode

        _, bus, cfg = rig_bus(rig, endpoint, need_config=True)
        robot = robot or next(iter(cfg.robots))
        if robot not in cfg.robots:
            raise UserError(f"rig {cfg.name} has no robot {robot!r}")
        try:
            adapter = load_adapter(checkpoint, method)
        except ValueError as e:
            raise UserError(str(e)) from None
        names = send_names(send, adapter)
        with AdaptationNode(adapter, cfg.name, robot, bus, send=names) as node:
            try:
                stats = node.run(max_updates=max_updates, idle_timeout_s=idle_timeout_s)
            except (TimeoutError, ValueError) as e:
                raise UserError(str(e)) from None
        s = stats.summary()
        if json_out:
            echo_json(s)
        else:
            typer.echo(" ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in s.items()
                                if k != "last_error") + (f"\nlast error: {s['last_error']}" if s["last_error"] else ""))
