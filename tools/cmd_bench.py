"""hil bench bus | plan | sim | adaptation | tracker | meld: speed goals as ratios against a peer in the same run;
hil bench fuzz: every parser of untrusted bytes under atheris; calibrate: a gauntlet."""

from __future__ import annotations

import json

import typer

from hilstack.tools.common import RAY_OPTION, UserError, echo_json, user_errors

bench_app = typer.Typer(help="Benchmarks (ratios against a peer in the same run).", no_args_is_help=True)


@bench_app.command("bus")
@user_errors
def bench_bus(
    n: int = typer.Option(2000, "--n", help="round trips per payload size"),
    via_router: bool = typer.Option(False, "--via-router", help="also raw Zenoh through a router process "
                                    "(`hil router`'s extra hop) beside the direct peer hop"),
    pin: bool = typer.Option(False, "--pin", help="ping on one CPU, every pong process on another (Linux): "
                             "each stack gets the same placement, so runs agree"),
    json_out: bool = typer.Option(False, "--json"),
) -> None:
    """Ping-pong latency: hilstack node layer vs raw zenoh-python (64 B and 4 KB)."""
    from hilstack.tools.bench_bus import run_bench_bus

    try:
        r = run_bench_bus(n=n, via_router=via_router, pin=pin)
    except ValueError as e:
        raise UserError(str(e)) from e
    if json_out:
        echo_json(r)
    else:
        typer.echo(json.dumps(r, indent=2))


@bench_app.command("plan")
@user_errors
def bench_plan(
    calls: int = typer.Option(50, "--calls"),
    json_out: bool = typer.Option(False, "--json"),
) -> None:
    """Planner timing on workloads A, B and baoding vs pytorch-mppi's MPPI (our model and a plain nn.Sequential one)."""
    from hilstack.tools.bench_plan import run_bench_plan

    r = run_bench_plan(calls=calls)
    echo_json(r) if json_out else typer.echo(json.dumps(r, indent=2))


@bench_app.command("sim")
@user_errors
def bench_sim(
    seconds: float = typer.Option(60.0, "--seconds", help="robot seconds to simulate"),
    json_out: bool = typer.Option(False, "--json"),
) -> None:
    """VelociRoACH sim speed in lockstep vs raw mj_step on the same model."""
    from hilstack.tools.bench_sim import run_bench_sim

    r = run_bench_sim(seconds_of_robot_time=seconds)
    echo_json(r) if json_out else typer.echo(json.dumps(r, indent=2))


@bench_app.command("adaptation")
@user_errors
def bench_adaptation(
    rig: str = typer.Option("roach_emulated", "--rig", help="a wall-clock (realtime) rig"),
    updates: int = typer.Option(100, "--updates", help="updates measured per payload"),
    payload: list[str] = typer.Option(None, "--payload", help="only these (repeatable): full, last_layer, context"),
    json_out: bool = typer.Option(False, "--json"),
) -> None:
    """State stamp → adapted model built at the MPC (p50/p99) per payload, vs raw Zenoh of the same bytes."""
    from hilstack.tools.bench_adaptation import PAYLOADS, run_bench_adaptation

    bad = [p for p in payload or [] if p not in PAYLOADS]
    if bad:
        raise UserError(f"--payload {bad[0]!r}: expected one of {list(PAYLOADS)}")
    if updates < 1:
        raise UserError(f"--updates must be at least 1, got {updates}")
    try:
        r = run_bench_adaptation(rig=rig, updates=updates, payloads=tuple(payload or PAYLOADS))
    except ValueError as e:
        raise UserError(str(e)) from None
    except RuntimeError as e:  # the rig or the node failed: one line, exit 1
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from None
    echo_json(r) if json_out else typer.echo(json.dumps(r, indent=2))


@bench_app.command("meld")
@user_errors
def bench_meld(
    episodes: int = typer.Option(2, "--episodes", help="random episodes per collection measurement"),
    steps: int = typer.Option(3, "--steps", help="gradient steps per learner and image size"),
    threads: int = typer.Option(2, "--threads", help="torch threads"),
    json_out: bool = typer.Option(False, "--json"),
) -> None:
    """MELD: collection samples/s with rendering (vs cameras off) and gradient steps/s per learner
    and image size (vs MELD at 32×64), on this machine."""
    from hilstack.tools.bench_meld import run_bench_meld

    r = run_bench_meld(episodes=episodes, steps=steps, threads=threads)
    echo_json(r) if json_out else typer.echo(json.dumps(r, indent=2))


@bench_app.command("fuzz")
@user_errors
def bench_fuzz(
    n: int = typer.Option(1_000_000, "--n", help="inputs per parser"),
    target: list[str] = typer.Option(None, "--target", help="only these targets (repeatable): xbee, mavlink, bus, "
                                     "robot_config, rig_config, task_config, reset_config, cli_args"),
    seed: int = typer.Option(1, "--seed", help="libFuzzer seed (same seed, same inputs)"),
    json_out: bool = typer.Option(False, "--json"),
) -> None:
    """Fuzz the parsers (XBee, MAVLink, bus), the config loaders and `hil`'s arguments (atheris); exit 1 on a crash."""
    from hilstack.tools.fuzz import TARGETS, run_bench_fuzz

    if n < 1:
        raise UserError(f"--n must be at least 1, got {n}")
    bad = [t for t in target or [] if t not in TARGETS]
    if bad:
        raise UserError(f"--target {bad[0]!r}: expected one of {sorted(TARGETS)}")
    r = run_bench_fuzz(n=n, targets=target or None, seed=seed)
    if json_out:
        echo_json(r)
    else:
        for name, t in r["targets"].items():
            typer.echo(f"{name}: inputs={t['inputs']} crashes={t['crashes']} inputs/s={t['inputs_per_s']}")
            if t["crashes"]:
                typer.echo("\n".join(f"  {ln}" for ln in t["crash"]["exception"] or t["crash"]["log_tail"]))
                typer.echo(f"  input (hex): {t['crash']['input_hex']}")
    if r["crashes"]:
        raise typer.Exit(1)


@bench_app.command("calibrate")
@user_errors
def bench_calibrate(
    seeds: int = typer.Option(20, "--seeds", help="seeds per case (each runs an effect and a clean version)"),
    cases: str | None = typer.Option(None, "--cases", help="comma-separated case names (default: all)"),
    out: str = typer.Option("bench_calibrate", "--out", help="directory for the generated data and reports"),
    workers: int = typer.Option(1, "--workers", help="Ray workers of a local runtime (> 1 without --ray: "
                                "a local Ray runtime)"),
    ray: str | None = RAY_OPTION,
    first_seed: int = typer.Option(0, "--first-seed", help="first seed (to run the seeds in batches)"),
    speed: bool = typer.Option(False, "--speed", help="instead of the gauntlet: the run time of one calibration of "
                               "a 10,000-sample recording (EMPS when found), batched replay vs one episode at a time"),
    json_out: bool = typer.Option(False, "--json"),
) -> None:
    """Realistic-data gauntlet for `hil calibrate`: hits, misses and false alarms over seeds."""
    from hilstack.tools.bench_calibrate import format_speed, format_table, run_bench_calibrate, run_speed

    if speed:
        res = run_speed(out, log=lambda s: typer.echo(s, err=True))
        if json_out:
            echo_json(res)
        else:
            typer.echo(format_speed(res))
        return
    try:
        r = run_bench_calibrate(seeds=seeds, cases=cases.split(",") if cases else None, out_dir=out, workers=workers,
                                first_seed=first_seed, ray=ray, log=lambda s: typer.echo(s, err=True))
    except KeyError as e:
        raise UserError(str(e.args[0])) from None
    if json_out:
        echo_json({"cases": r["cases"], "totals": r["totals"]})
    else:
        typer.echo(format_table(r))


@bench_app.command("tracker")
@user_errors
def bench_tracker(
    seconds: float = typer.Option(5.0, "--seconds", help="seconds of Baoding motion (10 frames per second)"),
    closed_loop_s: float = typer.Option(0.0, "--closed-loop", help="also run the hand sim closed loop this long [s]"),
    json_out: bool = typer.Option(False, "--json"),
) -> None:
    """Ball trackers on rendered Baoding motion: error vs truth and latency; learned vs colour, vs the thesis."""
    from hilstack.tools.bench_tracker import run_bench_tracker

    r = run_bench_tracker(seconds=seconds, closed_loop_s=closed_loop_s)
    echo_json(r) if json_out else typer.echo(json.dumps(r, indent=2))


def register(app: typer.Typer) -> None:
    app.add_typer(bench_app, name="bench")
