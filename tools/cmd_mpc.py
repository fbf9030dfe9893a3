"""hil mpc: the MPC node on any rig (lockstep sims, or realtime on real/emulated robots)."""

from __future__ import annotations

from pathlib import Path

import typer

from hilstack.tools.common import (
    EndpointOpt,
    UserError,
    complete_rig,
    echo_json,
    one_line,
    rig_bus,
    user_errors,
)


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def mpc(
        rig: str = typer.Argument(..., help="rig config (its driver node must be up: `hil up RIG`)", autocompletion=complete_rig),
        model: Path = typer.Option(None, "--model", exists=True, dir_okay=False, help="dynamics checkpoint (model.pt)"),
        adapt: Path = typer.Option(None, "--adapt", exists=True, dir_okay=False,
                                   help="adaptation checkpoint instead of --model: plan with its model and swap in "
                                        "the updates `hil adapt` publishes (docs/adaptation.md)"),
        method: str = typer.Option(None, "--method", help="with --adapt: override the checkpoint's method"),
        path: str = typer.Option("straight", "--path", help="straight | left | right | zigzag | figure8"),
        path_scale: float = typer.Option(1.5, "--path-scale"),
        speed: float = typer.Option(1.0, "--speed", help="bound on normalized commands, (0, 1]"),
        steps: int = typer.Option(100, "--steps"),
        planner: str = typer.Option("cem", "--planner", help="cem | random_shooting | pddm"),
        robot: str = typer.Option(None, "--robot", help="robot key in the rig (default: the only one)"),
        reset: bool = typer.Option(True, "--reset/--no-reset", help="ask the driver to reset to the path start (sim)"),
        refit_every: float = typer.Option(5.0, "--refit-every", help="realtime rigs: refit the planner's sample count "
                                          "to the load every this many seconds of control (0: keep the start's fit)"),
        json_out: bool = typer.Option(False, "--json"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """Follow a path with MPC over the bus; prints the path cost.

        Commands are published at the control rate; on realtime rigs late plans are
        replaced by the shifted last plan and counted. With --adapt, each plan starts with the
        newest model from hil/<rig>/model/update (run `hil adapt RIG --checkpoint C` beside it).
        On realtime rigs the planner's sample count is fitted to the period at the start and
        refitted to the measured plan times every --refit-every seconds (docs/mbrl.md)."""
        from types import SimpleNamespace

        import numpy as np

        from hilstack.control.controller_node import (
            REALTIME_DEADLINE_FRAC,
            ControllerNode,
            DriverGone,
            ResetFailed,
        )
        from hilstack.control.costs import PathCost, evaluate_path_following
        from hilstack.control.paths import fillet, make_path
        from hilstack.control.policies import MpcPolicy
        from hilstack.control.sample_refit import SampleRefit
        from hilstack.learning.frames import load_dynamics
        from hilstack.learning.mbrl import (
            MbrlConfig,
            PathEnd,
            fit_planner_to_period,
            make_planner,
            path_start_pose,
            task_cost,
        )

        if (model is None) == (adapt is None):
            raise UserError("give exactly one of --model (a fixed model) and --adapt (an adaptation checkpoint)")
        if method is not None and adapt is None:
            raise UserError("--method needs --adapt")
        if not 0 < speed <= 1:
            raise UserError("--speed must be in (0, 1]")
        if not (np.isfinite(refit_every) and 0 <= refit_every <= 3600):
            raise UserError(f"--refit-every must be in [0, 3600] s, got {refit_every}")
        _, bus, cfg = rig_bus(rig, endpoint, need_config=True)
        robot = robot or next(iter(cfg.robots))
        if robot not in cfg.robots:
            raise UserError(f"rig {cfg.name} has no robot {robot!r}")
        try:
            wp = make_path(path, scale=path_scale)
        except (KeyError, ValueError) as e:
            raise UserError(str(e)) from None
        adapter = swap = None
        if adapt is not None:
            from hilstack.learning.adaptation import load_adapter

            try:
                adapter = load_adapter(adapt, method)
            except ValueError as e:
                raise UserError(str(e)) from None
            except Exception as e:  # noqa: BLE001 - not a checkpoint at all (CSV, random bytes...)
                raise UserError(f"--adapt {adapt}: not an adaptation checkpoint ({type(e).__name__}: "
                                f"{one_line(e)})") from None
        else:
            try:
                dyn = load_dynamics(model)
            except Exception as e:  # noqa: BLE001 - torch/pickle say many things about a file that is not one
                raise UserError(f"--model {model}: not a dynamics checkpoint ({type(e).__name__}: "
                                f"{one_line(e)})") from None
        with ControllerNode(cfg.name, robot, bus, name="mpc", state_timeout_s=10.0) as ctl:
            if adapter is not None:
                from hilstack.bus import keys
                from hilstack.bus.schemas import ModelUpdate
                from hilstack.learning.adaptation.node import ModelSwap

                swap = ModelSwap(adapter, ctl.subscribe(keys.model_update(cfg.name), ModelUpdate))
                dyn = SimpleNamespace(predict=swap.initial())
            spec = ctl.wait_ready()
            names = list(spec.state.names)
            if adapter is not None and list(adapter.model.state_names) != names:
                raise UserError(f"{adapt} models states {list(adapter.model.state_names)}; robot {robot} has {names}")
            try:
                cost = PathCost(wp, names)
            except KeyError as e:  # a robot with no planar pose (an arm, the point mass's x, y only)
                raise UserError(f"rig {cfg.name} robot {robot}: `hil mpc` follows a planar path and needs the "
                                f"robot's position and heading in its state ({one_line(e)})") from None
            # as in `hil demo`: track the path with rounded corners, score on the path itself
            mcfg = MbrlConfig(planner=planner)
            ref = task_cost(mcfg, fillet(wp, mcfg.reference_corner_radius_m), names)
            n_act, max_step = spec.action.dim, spec.max_step_normalized()
            samples = refit = None
            lockstep = ctl.pacing.answered  # the robot's time model, from its spec
            if not lockstep:  # as in `hil demo`: the planner must fit the period on this machine
                timing_cost = PathCost(fillet(wp, mcfg.reference_corner_radius_m), names)
                samples, _ = fit_planner_to_period(mcfg, speed, n_act, max_step, dyn.predict, timing_cost,
                                                   np.asarray(ctl.next_state().state), spec.period_s)
                if refit_every > 0:  # the load changes within minutes: the count follows it
                    refit = SampleRefit(max_samples=mcfg.samples, min_samples=mcfg.realtime_min_samples,
                                        budget_s=mcfg.realtime_plan_budget * spec.period_s,
                                        deadline_s=REALTIME_DEADLINE_FRAC * spec.period_s,
                                        max_late_share=mcfg.realtime_max_late_share,
                                        every_steps=max(1, round(refit_every / spec.period_s)))
            planner_ = make_planner(mcfg, speed, n_act, max_step, samples)
            pol = MpcPolicy(dyn, planner_, ref, model_source=swap, delay_steps=ctl.pacing.command_delay_periods)
            try:
                first = ctl.reset(**path_start_pose(wp)) if reset else None
            except (ResetFailed, DriverGone, TimeoutError) as e:  # nothing was commanded: the robot is still
                typer.echo(f"error: {one_line(e)}; nothing was sent to the robot (start it where the path "
                           "starts and give --no-reset, or run the rig's reset supervisor)", err=True)
                raise typer.Exit(1) from None
            # lockstep: the episode ends at the path's end; realtime runs its steps
            log = ctl.run_episode(pol, steps, first, stop_if=PathEnd(PathCost(wp, names)) if lockstep else None,
                                  refit=refit)
        m = evaluate_path_following(np.array(log.states), cost, period_s=spec.period_s)
        m.update(samples=planner_.samples, samples_start=samples if samples is not None else planner_.samples,
                 sample_refits=len(log.sample_refits), late_plans=log.late_plans, plan_ms_p50=float(np.percentile(log.plan_times_s, 50) * 1e3)
                 if log.plan_times_s else None)
        if swap is not None:
            m["model_updates"] = swap.summary()
        if json_out:
            echo_json({**m, "sample_refit_log": log.sample_refits})
        else:
            typer.echo(" ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in m.items()))
