"""`hil export ros2 REC.mcap --out DIR`: a recording as a ROS 2 bag; `hil export lerobot REC.mcap|DIR
--out DIR`: recordings as a LeRobotDataset v3.0 (tools/export.py).

    hil export ros2 session.mcap --out session_bag          # rosbag2 directory, MCAP storage, CDR
    ros2 bag info session_bag                                # or rosbags: Reader(session_bag)
    hil export lerobot out/demo/recordings --out roach_ds    # every episode of every recording
"""

from __future__ import annotations

from pathlib import Path

import typer

from hilstack.tools.common import UserError, echo_json, user_errors

export_app = typer.Typer(help="Recordings in other tools' formats (ROS 2 bags, LeRobot datasets).", no_args_is_help=True)


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


@export_app.command("lerobot")
@user_errors
def lerobot(
    src: Path = typer.Argument(..., help="an MCAP recording or a directory of them"),
    out: Path = typer.Option(..., "--out", help="the dataset directory to create"),
    robot: str = typer.Option(None, "--robot", help="the robot to export (default: the only one)"),
    task: str = typer.Option("", "--task", help="the episodes' task text (default: the robot's name)"),
    force: bool = typer.Option(False, "--force", help="replace --out if it exists"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON line"),
) -> None:
    """A LeRobotDataset v3.0 (meta/info.json, episodes, parquet data), checked as lerobot's loader does."""
    from hilstack.tools.export import check_lerobot, export_lerobot

    res = export_lerobot(src, out, robot=robot, task=task, force=force)
    res["check"] = check_lerobot(out)
    if json_out:
        echo_json(res)
        return
    typer.echo(f"{out}: {res['episodes']} episodes, {res['frames']} frames at {res['fps']} fps "
               f"({res['robot_type']}); features {', '.join(res['check']['features'])}")


def register(app: typer.Typer) -> None:
    app.add_typer(export_app, name="export")
