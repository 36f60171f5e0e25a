"""Camera file commands: ``labrig import`` (Prophesee .raw / Metavision .hdf5 -> labrig recording)
and ``labrig export`` (recording -> EVT3 .raw that Prophesee tools read).

Mount on the main app with :func:`add_camera_commands`; the work is in :mod:`labrig.recording.convert`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Annotated

import typer
from rich.progress import TextColumn, TimeElapsedColumn, TimeRemainingColumn

from labrig.cli.console import JsonOption, console, err_console, print_json, progress_bar

OverwriteOption = Annotated[bool, typer.Option("--overwrite", help="Replace the output file if it exists.")]


@contextmanager
def _progress(description: str, disabled: bool) -> Iterator[Callable[[int, int, str], None]]:
    """A transient bar on a terminal (none with --json); yields the conversion's progress callback."""
    with progress_bar(TextColumn("{task.completed:,.0f}/{task.total:,.0f} {task.fields[unit]}"), TimeElapsedColumn(),
                      TimeRemainingColumn(), disable=disabled or not err_console.is_terminal, transient=True) as bar:
        task = None

        def update(done: int, total: int, unit: str) -> None:
            nonlocal task
            if task is None:
                task = bar.add_task(description, total=total, unit=unit)
            bar.update(task, completed=done)

        yield update


def import_command(
    file: Annotated[Path, typer.Argument(help="Prophesee RAW (.raw, EVT 3.0 / 2.0) or Metavision HDF5 (.hdf5).")],
    output: Annotated[Path, typer.Argument(help="labrig recording to write (.h5).")],
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Import a camera file into a labrig recording (events, trigger edges, source metadata)."""
    from labrig.recording.convert import import_file

    with _progress(f"import {file.name}", as_json) as progress:
        summary = import_file(file, output, overwrite=overwrite, progress=progress)
    if as_json:
        print_json(asdict(summary))
        return
    rate = summary.events / summary.elapsed_s / 1e6 if summary.elapsed_s > 0 else 0.0
    console.print(
        f"[green]imported[/] {summary.events:,} events and {summary.triggers} trigger edges "
        f"({summary.duration_s:.3f} s of {summary.source_format}) into {output} "
        f"in {summary.elapsed_s:.2f} s ({rate:.1f} Mev/s)",
        highlight=False,
    )
    if summary.skipped_words:
        console.print(f"[yellow]warning:[/] {summary.skipped_words} words of the RAW payload were not decoded")


def export_command(
    recording: Annotated[Path, typer.Argument(help="labrig recording (.h5).")],
    raw: Annotated[Path, typer.Option("--raw", help="Write the events as an EVT 3.0 RAW file here.")],
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Export a recording's camera events and trigger edges as an EVT 3.0 .raw (readable by Prophesee tools)."""
    from labrig.recording.convert import export_raw

    with _progress(f"export {recording.name}", as_json) as progress:
        summary = export_raw(recording, raw, overwrite=overwrite, progress=progress)
    if as_json:
        print_json(asdict(summary))
        return
    console.print(
        f"[green]exported[/] {summary.events:,} events and {summary.triggers} trigger edges to {raw} "
        f"({summary.output_bytes / 1e6:.1f} MB, {summary.bytes_per_event:.2f} B/event)",
        highlight=False,
    )


def add_camera_commands(app: typer.Typer) -> None:
    """Mount ``import`` and ``export`` on the main app."""
    app.command("import")(import_command)
    app.command("export")(export_command)
