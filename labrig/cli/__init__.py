"""The ``labrig`` command line: thin commands that parse, call the library and print with rich.

One module per command group mounts its commands on :data:`app`; :mod:`labrig.cli.console` holds
what they share (consoles, ``--json`` output, progress bars, Ctrl-C, common options). :func:`main`
is the console entry point: a :class:`LabrigError` prints one line and exits with its code.
"""

from __future__ import annotations

from typing import Annotated

import typer
from rich.markup import escape

from labrig import __version__
from labrig.cli.calibrate import add_calibrate_commands
from labrig.cli.camera import add_camera_commands
from labrig.cli.console import console, err_console
from labrig.cli.devices import add_device_commands
from labrig.cli.evaluate import add_evaluate_commands
from labrig.cli.groundtruth import add_groundtruth_commands
from labrig.cli.protocol import add_protocol_commands
from labrig.cli.recordings import add_recording_commands
from labrig.cli.run import add_run_commands
from labrig.cli.sim import add_sim_commands
from labrig.cli.train import add_train_commands
from labrig.errors import LabrigError

app = typer.Typer(
    name="labrig",
    help="Collect and evaluate datasets for dense 3D force estimation with an event-based tactile sensor.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        console.print(f"labrig {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version.")] = False,
) -> None:
    """labrig: probing rig, virtual rig, calibration, ground truth and evaluation."""


# `labrig --help` lists the commands in this order, then the groups (sim, cnc, calibrate).
add_recording_commands(app)
add_sim_commands(app)
add_device_commands(app)
add_camera_commands(app)
add_protocol_commands(app)
add_groundtruth_commands(app)
add_train_commands(app)
add_evaluate_commands(app)
add_run_commands(app)
add_calibrate_commands(app)


def main() -> None:
    """Console entry point: user errors print one line and exit 2, no traceback."""
    from labrig.recording.writer import exit_process

    code = 0
    try:
        app()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except LabrigError as exc:
        err_console.print(f"[red]error:[/] {escape(str(exc))}", soft_wrap=True, highlight=False)
        code = exc.exit_code
    except KeyboardInterrupt:
        err_console.print("[yellow]interrupted[/]")
        code = 130
    exit_process(code)
