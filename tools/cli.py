"""The `hil` command line. Each verb lives in its own module `tools/cmd_<verb>.py`
exposing `register(app)`, listed in `_VERB_MODULES` below."""

from __future__ import annotations

import importlib
import os

import typer

# On a shared 2-core machine OpenMP's default busy-wait collapses torch's threads when
# another process (the sim, a driver node) is busy: planner p99 went from ~100 ms to
# 400-800 ms in `hil bench plan`. Must be set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# Simulated cameras (hand stereo pair, WidowX bench) render offscreen; MuJoCo picks its GL
# platform when imported, so set it before any verb imports MuJoCo (PLATFORM_NOTES: EGL works headless).
os.environ.setdefault("MUJOCO_GL", "egl")


def _flags_shown_as_flags() -> None:
    """typer 0.29's help gives every boolean flag a type column (``--json <bool>``), as if it
    took a value; it takes none (``--json``, ``--reset/--no-reset``). Flags get no type column;
    every other option keeps its own (``--steps <int>``)."""
    from typer.core import TyperOption

    shown = TyperOption.display_type_rich
    if getattr(shown, "hil_flags", False):
        return

    def display_type_rich(self: TyperOption, ctx: typer.Context):  # noqa: ANN202 - typer's signature
        return None if self.is_flag else shown(self, ctx)

    display_type_rich.hil_flags = True  # type: ignore[attr-defined]
    TyperOption.display_type_rich = display_type_rich  # type: ignore[method-assign]


_flags_shown_as_flags()

app = typer.Typer(
    help="hilstack: hardware-in-the-loop robot stack for model-based learning and control.",
    no_args_is_help=True,
    add_completion=True,  # --install-completion / --show-completion (bash, zsh, fish, PowerShell)
    pretty_exceptions_enable=False,
)

# Order is the order `hil --help` lists them.
_VERB_MODULES = [
    "hilstack.tools.cmd_demo",
    "hilstack.tools.cmd_drive",
    "hilstack.tools.cmd_mpc",
    "hilstack.tools.cmd_teleop",
    "hilstack.tools.cmd_console",
    "hilstack.tools.cmd_adapt",
    "hilstack.tools.cmd_record",
    "hilstack.tools.cmd_export",
    "hilstack.tools.cmd_viz",
    "hilstack.tools.cmd_calibrate",
    "hilstack.tools.cmd_excite",
    "hilstack.tools.cmd_data",
    "hilstack.tools.cmd_bench",
    "hilstack.tools.cmd_misc",
    "hilstack.tools.cmd_doctor",
]

def version() -> str:
    """The installed hilstack version (package metadata), or the source tree's pyproject."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("hilstack")
    except PackageNotFoundError:  # run from a checkout that was never pip-installed
        import tomllib
        from pathlib import Path

        pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
        return tomllib.loads(pyproject.read_text())["project"]["version"]


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"hilstack {version()}")
        raise typer.Exit()


@app.callback()
def _root(
    _version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                  help="print the hilstack version and exit"),
) -> None:
    """hilstack: hardware-in-the-loop robot stack for model-based learning and control."""


for _mod in _VERB_MODULES:
    importlib.import_module(_mod).register(app)


def main() -> None:
    """The `hil` program (pyproject's console script and ``python -m hilstack``): ``app`` with
    the process-wide setup a verb run inside another process (tests' CliRunner) must not get."""
    import signal

    from hilstack.bus.lifetime import dump_stacks_on_signal
    from hilstack.tools import common

    dump_stacks_on_signal()  # `kill -USR1 PID`: where a stuck `hil` process is (stderr)
    common.HARD_EXIT_AFTER_ERROR = True  # after an error the process ends, whatever is left open
    # a job started in the background by a non-interactive shell inherits SIGINT ignored: Ctrl-C
    # or `kill -INT` would not stop a `hil demo` running there (verbs that drive a robot catch
    # stop signals themselves, bus/lifetime.py)
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    app()


if __name__ == "__main__":
    main()
