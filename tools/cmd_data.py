"""`hil data`: public data sets the examples use, found locally or downloaded (checksummed).

    hil data emps                      # prints the directory holding the EMPS files
    hil data emps --csv out/emps.csv   # ... and converts the estimation run for `hil calibrate`
    hil data emps --offline            # never touch the network ($HIL_DATA, cache, ../shared)
"""

from __future__ import annotations

from pathlib import Path

import typer

from hilstack.tools.common import EXIT_RUNTIME, UserError, echo_json, one_line, user_errors

data_app = typer.Typer(help="Public data sets used by the examples (checksummed, cached).", no_args_is_help=True)


@data_app.command("emps")
@user_errors
def emps(
    csv: Path = typer.Option(None, "--csv", help="also write DATA_EMPS.mat as CSV (time, volts, position)"),
    url: str = typer.Option(None, "--url", help="download from this base URL instead of the public one"),
    offline: bool = typer.Option(False, "--offline", help="only local copies ($HIL_DATA/emps, cache, ../shared)"),
    json_out: bool = typer.Option(False, "--json"),
) -> None:
    """The EMPS ball-screw axis data (real measurements): find or download, check, convert."""
    from hilstack.calibration.emps import DataError, DataNotFound, emps_to_csv, fetch_emps

    try:
        d = fetch_emps(base_url=url, offline=offline)
    except DataNotFound as e:
        raise UserError(str(e)) from None
    except DataError as e:  # the network or the file failed us, not the input
        typer.echo(f"error: {one_line(e)}", err=True)
        raise typer.Exit(EXIT_RUNTIME) from None
    out = {"dir": str(d), "files": sorted(str(p) for p in d.glob("DATA_EMPS*.mat"))}
    if csv is not None:
        out["csv"] = str(emps_to_csv(d / "DATA_EMPS.mat", csv))
    if json_out:
        echo_json(out)
    else:
        typer.echo(out.get("csv", out["dir"]))


def register(app: typer.Typer) -> None:
    app.add_typer(data_app, name="data")
