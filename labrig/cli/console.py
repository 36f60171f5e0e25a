"""What every ``labrig`` command shares: the consoles, ``--json`` output, progress bars, Ctrl-C and common options.

Commands print their human output with rich on :data:`console` (stdout), progress and notes on
:data:`err_console` (stderr), and their ``--json`` summary with :func:`print_json` (stdout, nothing
else there).
"""

from __future__ import annotations

import json
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, ProgressColumn, TextColumn

if TYPE_CHECKING:
    from labrig.config import RigConfig
    from labrig.indenters import Indenter
    from labrig.protocol.safety import StopRequest

console = Console()
err_console = Console(stderr=True)

JsonOption = Annotated[bool, typer.Option("--json", help="Print the summary as JSON (stable keys, units in names).")]
JsonResultOption = Annotated[bool, typer.Option("--json", help="Print the result as JSON (stable keys, units in names).")]
RigOption = Annotated[Path | None, typer.Option("--rig", help="Rig TOML (default: calibration/rig.toml).")]
IndentersOption = Annotated[Path | None, typer.Option("--indenters", help="Indenter TOML (default: protocols/indenters.toml).")]
CalibrationOption = Annotated[Path | None, typer.Option(
    "--calibration", help="Calibration folder: gel.toml, intrinsics.toml, extrinsics.toml, rig-registration.toml "
    "(default: the folder of labrig's default rig, wherever the command runs from).")]
WindowMsOption = Annotated[float | None, typer.Option(
    help="Fixed-time windows, ms (default 10; live: the network's trained window).")]
WindowEventsOption = Annotated[int | None, typer.Option(help="Fixed-count windows (the paper's evaluation: 20000).")]


def calibration_folder(calibration: Path | None) -> Path:
    """``--calibration``, checked (one clear line if it is not a folder), or the default rig's folder."""
    from labrig.config import DEFAULT_CALIBRATION_DIR
    from labrig.errors import LabrigError

    if calibration is None:
        return Path(DEFAULT_CALIBRATION_DIR)
    if not calibration.is_dir():
        raise LabrigError(f"--calibration {calibration}: not a folder; pass the folder holding the rig's gel.toml, "
                          "intrinsics.toml and extrinsics.toml")
    return calibration


def json_default(value: Any) -> Any:
    """numpy scalars and arrays as plain JSON values."""
    if hasattr(value, "item"):  # numpy scalars
        return value.item()
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


def print_json(data: Any, *, default: Callable[[Any], Any] = json_default) -> None:
    """``data`` as indented JSON on stdout (a command's ``--json`` summary)."""
    sys.stdout.write(json.dumps(data, indent=2, default=default) + "\n")


def print_json_line(data: Any) -> None:
    """``data`` as one JSON line on stdout, flushed (a stream of records, e.g. ``labrig sim serve --json``)."""
    sys.stdout.write(json.dumps(data, default=json_default) + "\n")
    sys.stdout.flush()


def progress_bar(*columns: ProgressColumn, disable: bool, transient: bool = False) -> Progress:
    """A progress bar on stderr: the task's description, the bar, then ``columns``."""
    return Progress(TextColumn("{task.description}"), BarColumn(), *columns, console=err_console, disable=disable,
                    transient=transient)


@contextmanager
def on_ctrl_c(action: Callable[[], str]) -> Iterator[None]:
    """Within the block, Ctrl-C runs ``action`` and prints what it returns instead of raising KeyboardInterrupt.

    Off the main thread (where signal handlers cannot be set) Ctrl-C keeps its default.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        err_console.print(action())

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextmanager
def on_terminate(stop: StopRequest) -> Iterator[None]:
    """Within the block, SIGTERM asks ``stop`` to hold and retract at once (as a second Ctrl-C), so
    the current recording is finalized as aborted and the command ends cleanly; off the main thread
    SIGTERM keeps its default."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        while stop.request() < 2:
            pass
        err_console.print("[red]terminated: holding and retracting now, then stopping[/]")

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def stop_probing_run(stop: StopRequest) -> Callable[[], str]:
    """The Ctrl-C action of a probing run: first finish the phase and stop, then hold and retract at once."""

    def action() -> str:
        if stop.request() == 1:
            return "[yellow]stopping after this phase[/] (Ctrl-C again to hold and retract at once)"
        return "[red]holding and retracting now[/]"

    return action


def load_rig_and_indenters(rig_path: Path | None, indenters_path: Path | None) -> tuple[RigConfig, dict[str, Indenter], Path]:
    """The rig file (default ``calibration/rig.toml``), its indenters and the indenter file they came from."""
    from labrig.config import DEFAULT_RIG, load_rig
    from labrig.indenters import DEFAULT_INDENTERS, load_indenters

    path = Path(indenters_path or DEFAULT_INDENTERS)
    return load_rig(rig_path or DEFAULT_RIG), load_indenters(path), path
