"""hil demo: the README's main job."""

from __future__ import annotations

from pathlib import Path

import typer

from hilstack.tools.common import RAY_OPTION, UserError, user_errors

#: The demos besides the roach MBRL one: name → (module, function, one-line help). Each
#: function takes ``(out, quick=, full=, seed=)`` and prints its own summary.
OTHER_DEMOS: dict[str, tuple[str, str, str]] = {
    "transfer": ("hilstack.tools.demo_transfer", "cli_transfer", "SIDM and GAT/GARAT (docs/transfer.md)"),
    "adaptation": ("hilstack.tools.demo_adaptation", "cli_adaptation", "GrBAL, ReBAL, MB+DE, MOLe (docs/adaptation.md)"),
    "baoding": ("hilstack.tools.demo_baoding", "cli_baoding", "PDDM on the Shadow Hand's Baoding balls (docs/baoding.md)"),
    "arms": ("hilstack.tools.demo_arms", "cli_arms", "reach with a learned model + MPC vs IK and random, WidowX and Sawyer (docs/arms.md)"),
    "meld": ("hilstack.tools.demo_meld", "cli_meld", "MELD vs SLAC and SAC on image history, WidowX port and Sawyer reacher from cameras (docs/meld.md)"),
    "mbrl-gym": ("hilstack.tools.demo_mbmf", "cli_mbrl_gym", "MB, MF (TRPO) and Mb-Mf on swimmer, half-cheetah, hopper, "
                 "ant (docs/mbrl.md)"),
}


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def demo(
        what: str = typer.Argument("roach", help="roach (MBRL) | " + " | ".join(
            f"{k} ({v[2]})" for k, v in OTHER_DEMOS.items())),
        out: Path = typer.Option(Path("out/demo"), "--out", help="output directory"),
        quick: bool = typer.Option(False, "--quick", help="smaller run (< 10 min on 2 cores)"),
        full: bool = typer.Option(False, "--full", help="also the thesis' Table 3.1, Fig. 3.8 speed sweep and "
                                  "Table 3.2 over 3 seeds (hours on 2 cores)"),
        world_frame: bool = typer.Option(False, "--world-frame",
                                         help="learn in the world frame (x, y ignored) instead of the body frame"),
        thesis_sampling: bool = typer.Option(False, "--thesis-sampling",
                                             help="random data and random shooting as in the thesis: independent "
                                                  "uniform steps (no holds, no forward commands, no rate limit)"),
        seed: int = typer.Option(0, "--seed"),
        tip_weight: float | None = typer.Option(None, "--tip-weight",
                                                help="roach: weight (1/rad) of the planner's tipping term "
                                                     "(docs/mbrl.md; 0 = the thesis' cost) [default: 50]"),
        tilt_loss_weight: float | None = typer.Option(None, "--tilt-loss-weight",
                                                      help="roach: weight of the tilt channels in the model's "
                                                           "training loss (docs/mbrl.md, Tipping) [default: 1]"),
        part: str = typer.Option("all", "--part", help="transfer: all | sidm | garat (one half of the demo); "
                                 "roach: terrain (the image-conditioned model on four terrains, Table 3.2, "
                                 "docs/mbrl.md)"),
        setting: str = typer.Option("roach", "--setting", help="transfer --part sidm only: roach (VelociRoACH pairs) | "
                                    "wheeled (the SIDM paper's wheeled robots with suspension)"),
        suite: str = typer.Option("roach", "--suite", help="adaptation only: roach (the sim VelociRoACH) | gym "
                                  "(half-cheetah benchmarks of the thesis)"),
        envs: str = typer.Option("", "--envs", help="mbrl-gym only: comma-separated swimmer, half_cheetah, hopper, "
                                 "ant (default: all four; --quick: half_cheetah)"),
        planner: str = typer.Option("cem", "--planner", help="cem | random_shooting | pddm"),
        rig: str | None = typer.Option(None, "--rig", help="rig config. roach: roach_sim (lockstep, the default), "
                                       "roach_emulated, roach_real; baoding: hand_sim (lockstep, the default), "
                                       "hand_sim_arm, hand_emulated (the hand in the loop, docs/baoding.md)"),
        operator_resets: bool = typer.Option(False, "--operator-resets",
                                             help="rigs without a reset: section (docs/reset.md): prompt an operator to place the robot"),
        ray: str | None = RAY_OPTION,
        workers: int = typer.Option(1, "--workers", help="with --ray local: the local runtime's CPUs"),
        resume: bool = typer.Option(False, "--resume", help="baoding only: continue the stopped run in --out "
                                    "after its last finished iteration (same preset and seed; --iterations, "
                                    "--extra-data and --extra-repeat may change)"),
        extra_data: list[Path] | None = typer.Option(None, "--extra-data", help="baoding only: a directory of "
                                                      "recorded episodes (its finished *.mcap) mixed into every "
                                                      "iteration's training split, never validation; repeatable "
                                                      "(docs/baoding.md: demonstrations, not the thesis' method)"),
        iterations: int | None = typer.Option(None, "--iterations", help="baoding only: PDDM iterations "
                                              "(default the preset's; a resumed run may be given more)"),
        extra_repeat: int = typer.Option(1, "--extra-repeat", help="baoding only: each --extra-data episode this "
                                         "many times in the training split"),
        targets: str | None = typer.Option(None, "--targets", help="baoding only: lead (the default: the targets "
                                           "run at most 60° ahead of the pair) | clock (the reference code's: by "
                                           "the step counter alone; docs/baoding.md)"),
        hold_pose: str | None = typer.Option(None, "--hold-pose", help="baoding only: pddm (the PDDM reference code's keyframe, "
                                             "rig hand_sim_pddm_pose: the thesis preset's default) | cupped (ours, "
                                             "rig hand_sim: --quick's default); without it --rig's pose "
                                             "(docs/baoding.md)"),
    ) -> None:
        """MBRL on the simulated VelociRoACH with every node on the bus; writes a report.

        Collects random data through the driver bridge, trains a dynamics model, runs MPC
        and the differential-drive baseline on five paths at a low and a high speed.
        The other demos (`hil demo transfer`, ...) are listed in OTHER_DEMOS."""
        if what == "roach" and part == "terrain":
            from hilstack.tools.demo_terrain import cli_terrain

            try:
                cli_terrain(out, quick=quick, full=full, seed=seed)
            except (ValueError, TimeoutError) as e:
                raise UserError(f"hil demo roach --part terrain: {e}") from None
            return
        if part != "all" and what != "transfer":
            raise UserError(f"hil demo {what}: --part is for the transfer demo only "
                            "(besides `hil demo roach --part terrain`)")
        if part not in ("all", "sidm", "garat"):
            raise UserError(f"hil demo transfer: unknown --part {part!r} (all | sidm | garat)")
        if setting not in ("roach", "wheeled"):
            raise UserError(f"hil demo transfer: unknown --setting {setting!r} (roach | wheeled)")
        if setting != "roach" and (what != "transfer" or part != "sidm"):
            raise UserError("hil demo: --setting is for `hil demo transfer --part sidm` only")
        if suite != "roach" and what != "adaptation":
            raise UserError(f"hil demo {what}: --suite is for the adaptation demo only")
        if suite not in ("roach", "gym"):
            raise UserError(f"hil demo adaptation: unknown --suite {suite!r} (roach | gym)")
        if envs and what != "mbrl-gym":
            raise UserError(f"hil demo {what}: --envs is for the mbrl-gym demo only")
        if ray is not None and what not in ("roach", "baoding", "adaptation", "transfer"):
            raise UserError(f"hil demo {what}: --ray is for the roach and baoding (--full), adaptation and "
                            "transfer demos only so far (docs/scaling.md)")
        if ray is not None and what in ("roach", "baoding") and not full:
            raise UserError(f"hil demo {what}: --ray is for the full run (--full); the other runs are one task")
        if ray is not None and suite == "gym":
            raise UserError("hil demo adaptation --suite gym: --ray is for the roach suite only so far")
        if rig is not None and what not in ("roach", "baoding"):
            raise UserError(f"hil demo {what}: --rig is for the roach and baoding demos only")
        if what in OTHER_DEMOS:
            import importlib

            module, fn, _ = OTHER_DEMOS[what]
            if resume and what != "baoding":
                raise UserError(f"hil demo {what}: --resume is for the baoding demo only")
            if (extra_data or extra_repeat != 1 or iterations is not None or targets is not None
                    or hold_pose is not None) and what != "baoding":
                raise UserError(f"hil demo {what}: --extra-data/--extra-repeat/--iterations/--targets/--hold-pose are "
                                "for the baoding demo only")
            kw = {"part": part, "setting": setting, "ray": ray, "workers": workers} if what == "transfer" else (
                {"suite": suite, "ray": ray, "workers": workers} if what == "adaptation" else (
                    {"ray": ray, "workers": workers, "resume": resume, "rig": rig, "extra_data": extra_data,
                     "extra_repeat": extra_repeat, "iterations": iterations, "targets": targets, "hold_pose": hold_pose}
                    if what == "baoding" else {}))
            if what == "mbrl-gym":
                from hilstack.tools.demo_mbmf import parse_envs

                try:
                    parse_envs(envs, quick)
                except ValueError as e:
                    raise UserError(f"hil demo mbrl-gym: {e}") from None
                kw = {"envs": envs or None}
            return getattr(importlib.import_module(module), fn)(out, quick=quick, full=full, seed=seed, **kw)
        if what != "roach":
            raise UserError(f"hil demo: unknown demo {what!r} ({' | '.join(['roach', *OTHER_DEMOS])})")
        if resume or extra_data or extra_repeat != 1 or iterations is not None or targets is not None \
                or hold_pose is not None:
            raise UserError("hil demo roach: --resume/--extra-data/--extra-repeat/--iterations/--targets/--hold-pose "
                            "are for the baoding demo only")
        from hilstack.learning.mbrl import RigError
        from hilstack.tools.demo import run_demo

        variant: dict = {}
        if world_frame:
            variant["body_frame"] = False
        if tip_weight is not None:
            variant["tip_weight"] = tip_weight
        if tilt_loss_weight is not None:
            variant["tilt_loss_weight"] = tilt_loss_weight
        if thesis_sampling:
            variant.update(random_hold_steps=1, random_forward_fraction=0.0, reachable_set=False)
        try:
            r = run_demo(out, quick=quick, full=full, seed=seed, planner=planner, rig=rig or "roach_sim",
                         operator_resets=operator_resets, ray=ray, workers=workers, **variant)
        except (RigError, ValueError) as e:
            typer.echo(f"error: {e}", err=True)
            raise typer.Exit(1) from None
        for s in ("low_speed", "high_speed"):
            if s in r:
                v, n = r[s], len(r[s]["paths"])
                typer.echo(f"{s}: completed mpc {v['mpc_completed']}/{n} differential_drive "
                           f"{v['differential_drive_completed']}/{n}; cost_per_m mpc {v['mpc_cost_per_m']:.1f} "
                           f"differential_drive {v['differential_drive_cost_per_m']:.1f} (tuned)")
        typer.echo(f"report: {out / 'report.md'}")
