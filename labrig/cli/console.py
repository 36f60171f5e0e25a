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


def output_file(value: Path | None) -> Path | None:
    """An output file option (``--plot``, ``--view``), checked as it is parsed, before any work: its folder is
    made; a folder in its place, or a file where its folder should be, is one clear line."""
    from labrig.errors import LabrigError

    if value is None:
        return None
    if value.is_dir():
        raise LabrigError(f"{value} is a folder; give a file name in it (e.g. {value / 'plot.png'})")
    try:
        value.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise LabrigError(f"cannot write {value}: {value.parent} is a file, not a folder") from None
    except OSError as exc:
        raise LabrigError(f"cannot write {value}: {exc.strerror or exc}") from None
    return value


def output_folder(value: Path, option: str) -> Path:
    """An output folder option (``--out``), made if missing; a file in its place is one clear line."""
    from labrig.errors import LabrigError

    if value.exists() and not value.is_dir():
        raise LabrigError(f"{option} {value} is a file; give a folder (it is made if missing)")
    try:
        value.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise LabrigError(f"{option} {value}: a file is in the way of the folder") from None
    except OSError as exc:
        raise LabrigError(f"{option} {value}: cannot make the folder ({exc.strerror or exc})") from None
    return value


def calibration_output(out: Path | None, default: Path, force: bool) -> Path:
    """Where a calibration is written: ``--out``, else ``default`` (the file beside the rig file, which the
    commands read). An existing default is replaced only with ``--force``; checked before any work."""
    from labrig.errors import CalibrationError

    if out is not None:
        return out
    if default.exists() and not force:
        raise CalibrationError(f"{default} exists: give --out FILE for a new calibration, or --force to replace it "
                               f"(the old one is kept as {default.name}.bak)")
    return default


ForceOption = Annotated[bool, typer.Option("--force", help=(
    "Replace the calibration beside the rig file when no --out is given (the old file is kept as NAME.bak)."))]


def calibration_file_rows(table: Any, summary: dict[str, Any]) -> None:
    """Rows of a calibration's rich table for the files it wrote besides its own (named in the title): plots,
    maps, the kept previous file."""
    for key, label in (("plot", "plot"), ("residual_map", "residual map"), ("backup", "previous file kept as")):
        if summary.get(key):
            table.add_row(label, str(summary[key]))


def keep_backup(path: Path) -> Path | None:
    """Copy ``path`` to ``NAME.bak`` beside it before it is replaced; None if there is nothing to keep."""
    import shutil

    if not path.is_file():
        return None
    backup = path.with_name(path.name + ".bak")
    shutil.copyfile(path, backup)
    return backup


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
