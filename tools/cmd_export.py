"""`hil export ros2 REC.mcap --out DIR`: a recording as a ROS 2 bag (tools/export.py).

    hil export ros2 session.mcap --out session_bag          # rosbag2 directory, MCAP storage, CDR
    ros2 bag info session_bag                                # or rosbags: Reader(session_bag)
"""

from __future__ import annotations

from pathlib import Path

import typer

from hilstack.tools.common import UserError, echo_json, user_errors

export_app = typer.Typer(help="Recordings in other tools' formats (ROS 2 bags).", no_args_is_help=True)


@export_app.command("ros2")
@user_errors
def ros2(
    rec: Path = typer.Argument(..., help="an MCAP recording (hil record, hil demo)"),
    out: Path = typer.Option(..., "--out", help="the bag directory to create"),
    force: bool = typer.Option(False, "--force", help="replace --out if it exists"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON line"),
) -> None:
    """A ROS 2 bag (MCAP, CDR) with standard messages: JointState, PoseStamped, TwistStamped, CompressedImage."""
    from hilstack.tools.export import export_ros2

    if not rec.is_file():
        raise UserError(f"{rec}: no such recording")
    res = export_ros2(rec, out, force=force)
    if json_out:
        echo_json(res.__dict__)
        return
    typer.echo(f"{out}: {res.messages} messages on {len(res.topics)} topics"
               + (f" ({res.skipped} skipped: no spec before them)" if res.skipped else ""))
    for topic, (typ, n) in sorted(res.topics.items()):
        typer.echo(f"  {topic:44s} {typ:36s} {n}")


def register(app: typer.Typer) -> None:
    app.add_typer(export_app, name="export")
