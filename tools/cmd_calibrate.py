"""`hil calibrate`: find what the nominal model lacks in measured data (see docs/calibration.md);
`hil calibrate-camera`: the stereo tracker's cameras (docs/camera.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import typer


def _calibrate_mjcf(data: Path, model: str, out: Path, seed: int, quiet: bool, as_json: bool, force: bool,
                    base: Path | None = None, current: bool = False) -> None:
    from hilstack.calibration.data import DataError
    from hilstack.calibration.mjcf_robot import SysidNotAvailable, run_mjcf_calibration
    from hilstack.configs.schema import ConfigError

    if not data.exists():
        _fail(f"--data {data}: no such file")
    try:
        rep = run_mjcf_calibration(data, model, out, seed=seed, progress=not quiet, force=force, base=base,
                                   current=current)
    except (DataError, SysidNotAvailable, ConfigError, ValueError) as e:
        _fail(str(e).splitlines()[0])
    summary = {k: rep[k] for k in ("effects", "values", "intervals_95", "unidentifiable", "pruned",
                                   "before_multi_step_nrmse", "after_multi_step_nrmse", "ratio",
                                   "calibrated_mjcf", "base", "outputs", "wall_s", "cpu_s")}
    if as_json:
        print(json.dumps(summary))
        return
    print(f"effects: {', '.join(rep['effects']) or 'none'}")
    for name, vals in rep["values"].items():
        ci = rep["intervals_95"][name]
        shown = ", ".join(f"{v:.4g}±{h:.2g}" for v, h in zip(vals, ci, strict=True))
        flag = f" (unidentifiable: {', '.join(rep['unidentifiable'][name])})" if name in rep["unidentifiable"] else ""
        print(f"  {name}: {shown}{flag}")
    print(f"held-out multi-step NRMSE: {rep['before_multi_step_nrmse']:.4f} -> {rep['after_multi_step_nrmse']:.4f} "
          f"(x{rep['ratio']:.3f})")
    if rep["outputs"] == "position+current":
        print(f"  (position and current; the position alone: {rep['before_position_nrmse']:.4f} -> "
              f"{rep['after_position_nrmse']:.4f})")
    print(f"calibrated MJCF: {rep['calibrated_mjcf']}; report: {out / 'report.md'}")


def register(app: typer.Typer) -> None:
    @app.command("calibrate")
    def calibrate(
        data: Path = typer.Option(..., "--data", help="CSV/Parquet file, a directory of them, or an .mcap recording"),
        model: str = typer.Option("axis", "--model",
                                  help="nominal model: a robot config YAML (its own MuJoCo model: writes "
                                       "OUT/calibrated.xml), axis, velociroach (MuJoCo sim; needs .mcap or full-state "
                                       "episodes), or a learned dynamics checkpoint PATH.pt (same as --model "
                                       "checkpoint --checkpoint PATH.pt): an effect is then a missing input"),
        checkpoint: Path | None = typer.Option(None, "--checkpoint",
                                               help="--model checkpoint: the EnsembleDynamics .pt file"),
        epochs: int | None = typer.Option(None, "--epochs",
                                          help="checkpoint: training epochs of every retrain (default 40)"),
        actions: str | None = typer.Option(
            None, "--actions", help="checkpoint + .mcap: actions 'normalized' to [-1, 1] of the spec (hilstack.learning.mbrl, "
                                    "default) or 'raw' robot units, as the checkpoint was trained"),
        column_map: str | None = typer.Option(
            None, "--map",
            help="column map t=..,u=..,x=..[,v=..,vbat=..,m=..,episode=..] or a YAML file with these keys "
                 "(CSV/Parquet default: t=time,u=volts,x=position; MCAP: optional, names recorded channels); "
                 "checkpoint + CSV: NAME=column for the checkpoint's state/action names, t=, episode=, vbat="),
        nominal: Path | None = typer.Option(
            None, "--nominal", help="velociroach: nominal robot config YAML (default: the backend's defaults)"),
        robot: str | None = typer.Option(None, "--robot", help="MCAP: which robot, when the recording has several"),
        out: Path = typer.Option(Path("calibration_out"), "--out", help="output directory for the report"),
        seed: int = typer.Option(0, "--seed", help="seed of the episode split and bootstraps"),
        ku: float | None = typer.Option(None, "--ku", help="known actuator gain (force per command unit, e.g. N/V)"),
        sg_window: int | None = typer.Option(None, "--sg-window", help="Savitzky-Golay window [samples] for velocity"),
        as_json: bool = typer.Option(False, "--json", help="print one JSON line instead of a summary"),
        quiet: bool = typer.Option(False, "--quiet", help="no progress on stderr"),
        force: bool = typer.Option(False, "--force", help="robot config: overwrite OUT/calibrated.xml"),
        base: Path | None = typer.Option(
            None, "--base", help="robot config: judge effects against a previous calibration (its OUT directory "
                                 "or calibrated.xml), e.g. the clean rig's, instead of the MJCF as shipped"),
        current: bool = typer.Option(
            False, "--current", help="robot config with velocity-loop servos (WidowX): fit and score the reported "
                                     "motor current beside the joint positions (a viscous loss shows there)"),
    ) -> None:
        """Replay measured commands through the model, test the effect catalogue, report before/after."""
        from hilstack.calibration import DataError, ModelNotAvailable, UnknownModel, run_calibration

        if model.endswith((".yaml", ".yml")):  # a robot config: calibrate the robot's own MJCF
            _calibrate_mjcf(data, model, out, seed, quiet, as_json, force, base, current)
            return
        if base is not None or current:
            _fail("--base and --current are for --model <robot config> (the robot's own MJCF)")

        if sg_window is not None and (sg_window < 5 or sg_window % 2 == 0):
            _fail("--sg-window must be an odd number of samples >= 5")
        learned = model == "checkpoint" or model.endswith(".pt")
        if column_map is None and data.suffix.lower() != ".mcap" and not learned:
            column_map = "t=time,u=volts,x=position"
        opts = {"nominal": str(nominal)} if nominal is not None else None
        if learned:
            if model == "checkpoint" and checkpoint is None:
                _fail("--model checkpoint needs --checkpoint PATH (or pass the .pt path as --model)")
            if actions not in (None, "normalized", "raw"):
                _fail("--actions must be 'normalized' or 'raw'")
            opts = {"checkpoint": str(checkpoint if model == "checkpoint" else model), "epochs": epochs,
                    "normalized_actions": None if actions is None else actions == "normalized"}
            opts = {k: v for k, v in opts.items() if v is not None}
            model = "checkpoint"
        try:
            report = run_calibration(data, model=model, column_map=column_map, out_dir=out, seed=seed,
                                     progress=not quiet, k_u=ku, sg_window=sg_window, model_options=opts,
                                     robot=robot)
        except (DataError, UnknownModel, ModelNotAvailable) as e:
            _fail(str(e))
        for w in report.get("warnings", []):
            print(f"warning: {w}", file=sys.stderr)
        summary = {
            "verdict": report["verdict"],
            "effects": [{"name": e["name"], "params": e["params"], "heldout_gain": e["heldout_gain"],
                         "evidence": (e.get("evidence") or {}).get("level"),
                         "gain_interval": (e.get("evidence") or {}).get("interval"),
                         "p_value": e["p_value"]} for e in report["effects"]],
            "findings": [{k: f[k] for k in ("name", "level", "heldout_gain", "interval")}
                         for f in report.get("findings", [])],
            "ambiguous": [a["effects"] for a in report["ambiguous"]],
            "unexplained_structure": report["unexplained_structure"],
            "before_multi_step_nrmse": report["before"]["multi_step_nrmse"]["mean"],
            "after_multi_step_nrmse": report["after"]["multi_step_nrmse"]["mean"],
            "report": str(Path(out) / "report.json"),
        }
        if report.get("augmented_model"):
            summary["augmented_model"] = report["augmented_model"]["path"]
        if as_json:
            typer.echo(json.dumps(summary))
            return
        typer.echo(f"verdict: {summary['verdict']}" + ("" if report["effects"] else " (nothing found)"))
        for e in report["effects"]:
            ps = ", ".join(f"{k}={v:.4g}" for k, v in e["params"].items() if v is not None)
            evd = e.get("evidence") or {}
            iv = evd.get("interval") or [float("nan")] * 2
            typer.echo(f"  {e['name']}: {ps} (evidence {evd.get('level', 'n/a')}: held-out gain {e['heldout_gain']:.3f}"
                       f" [{iv[0]:.3f}, {iv[1]:.3f}])")
        for f in report.get("findings", []):
            typer.echo(f"  {f['level']} finding (not added): {f['name']} (held-out gain {f['heldout_gain']:+.3f} "
                       f"[{f['interval'][0]:+.3f}, {f['interval'][1]:+.3f}])")
        for a in report["ambiguous"]:
            typer.echo(f"  ambiguous: {' vs '.join(a['effects'])} -> {a['excitation']}")
        typer.echo(f"unexplained structure: {summary['unexplained_structure']}")
        b, a = summary["before_multi_step_nrmse"], summary["after_multi_step_nrmse"]
        typer.echo(f"multi-step NRMSE (locked test set): before {'n/a' if b is None else f'{b:.4f}'}, "
                   f"after {'n/a' if a is None else f'{a:.4f}'}")
        if report.get("augmented_model"):
            am = report["augmented_model"]
            typer.echo(f"augmented model: {am['path']} (extra inputs: "
                       f"{', '.join(e['name'] for e in am['extra_inputs']) or 'none'})")
        if report.get("closing_the_loop"):
            typer.echo(f"calibrated sim config: {report['closing_the_loop']['sim_params_yaml']}")
        typer.echo(f"report: {out}/report.md")


    @app.command("calibrate-camera")
    def calibrate_camera(
        camera_id: str = typer.Option("stereo0", "--camera-id", help="the pair's id: names the result file"),
        out: Path = typer.Option(Path("calibration_out/camera"), "--out",
                                 help="directory for <camera-id>.json (an older one is kept, renamed)"),
        images: Path | None = typer.Option(
            None, "--images", help="real pairs: a directory of left_*.png / right_*.png (default: rendered views)"),
        views: int = typer.Option(20, "--views", help="rendered: board poses to render"),
        seed: int = typer.Option(0, "--seed", help="rendered: seed of the board poses"),
        inner: str = typer.Option("7x4", "--inner", help="real: inner corners COLSxROWS of the printed board"),
        square_mm: float = typer.Option(10.0, "--square-mm", help="real: square size of the printed board [mm]"),
        fixture: str | None = typer.Option(None, "--fixture",
                                           help="real: suffix of the pair with the board in the fixture pose"),
        fixture_pose: str | None = typer.Option(
            None, "--fixture-pose", help="real: the fixture pose in the hand frame, x,y,z[m],rx,ry,rz[rad, rotation "
                                         "vector]"),
        as_json: bool = typer.Option(False, "--json", help="print one JSON line"),
    ) -> None:
        """Stereo intrinsics + extrinsics from checkerboard views, and the pair's pose on the hand.

        Without --images it renders the board in the MuJoCo hand scene and reports the error
        against the exact camera model."""
        import numpy as np

        from hilstack.calibration.camera import CalibrationError, calibrate_from_images, calibrate_rendered
        from hilstack.calibration.camera.stereo import BoardModel

        try:
            if images is None:
                if views < 6:
                    _fail("--views must be at least 6")
                cal, errors = calibrate_rendered(views=views, seed=seed, camera_id=camera_id)
            else:
                try:
                    cols, rows = (int(v) for v in inner.lower().split("x"))
                except ValueError:
                    _fail(f"--inner must be COLSxROWS (e.g. 7x4), got {inner!r}")
                pose = None
                if fixture_pose is not None:
                    import cv2

                    from hilstack.perception.geometry import homogeneous

                    try:
                        v = [float(x) for x in fixture_pose.split(",")]
                        assert len(v) == 6 and all(np.isfinite(v))
                    except (ValueError, AssertionError):
                        _fail(f"--fixture-pose must be six numbers x,y,z,rx,ry,rz, got {fixture_pose!r}")
                    pose = homogeneous(cv2.Rodrigues(np.array(v[3:]))[0], v[:3])
                cal = calibrate_from_images(images, BoardModel((cols, rows), square_mm / 1000), camera_id,
                                            fixture=fixture, hand_from_board=pose)
                errors = None
        except CalibrationError as e:
            _fail(str(e))
        path = cal.save(out)
        summary = {"camera_id": cal.camera_id, "timestamp": cal.timestamp, "file": str(path),
                   "rms_px": cal.report["rms_px"], "views_used": cal.report["views_used"],
                   "baseline_mm": 1000 * cal.baseline_m, "error_vs_truth": errors}
        if as_json:
            typer.echo(json.dumps(summary))
            return
        typer.echo(f"{cal.camera_id}: baseline {summary['baseline_mm']:.2f} mm, RMS {summary['rms_px']:.3f} px "
                   f"over {summary['views_used']} views -> {path}")
        for k, v in (errors or {}).items():
            typer.echo(f"  {k}: {v:.3f}")


def _fail(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr)
    raise typer.Exit(code=2)
