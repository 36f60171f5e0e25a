"""Camera file commands: ``labrig import`` (Prophesee .raw / Metavision .hdf5 -> labrig recording)
and ``labrig export`` (recording -> EVT3 .raw that Prophesee tools read).

Mount on the main app with :func:`add_camera_commands` (``cli.py``).

An imported file has no host clock: the recording's host times (``t_host_us`` of the event
packets) are the device times counted from the first event, so the stored camera clock model
is the identity plus an offset. The recording's ``extra_source_*`` attributes name the source.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import numpy.typing as npt
import typer
from rich.console import Console

from labrig.errors import LabrigError

console = Console()
err_console = Console(stderr=True)

JsonOption = Annotated[bool, typer.Option("--json", help="Print the summary as JSON (stable keys, units in names).")]
OverwriteOption = Annotated[bool, typer.Option("--overwrite", help="Replace the output file if it exists.")]

HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
#: Events put into the recording writer but not yet written, at most (backpressure on import).
MAX_IN_FLIGHT_EVENTS = 1 << 22
#: Events per slice when reading a recording for export.
EXPORT_SLICE_EVENTS = 1 << 20
#: Payload bytes per read when importing a RAW file.
IMPORT_READ_BYTES = 16 << 20


def _print_json(data: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(data, indent=2) + "\n")


def _progress(disabled: bool) -> Any:
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:,.0f}/{task.total:,.0f} {task.fields[unit]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=True,
        disable=disabled or not err_console.is_terminal,
    )


# -- import ------------------------------------------------------------------------------------


def _sniff(path: Path) -> str:
    """'hdf5' or 'raw' from the file's first bytes; LabrigError when it is neither."""
    if not path.exists():
        raise LabrigError(f"{path}: no such file")
    if not path.is_file():
        raise LabrigError(f"{path} is not a file")
    with open(path, "rb") as f:
        head = f.read(8)
    if head == HDF5_SIGNATURE:
        return "hdf5"
    if head.startswith(b"% "):
        return "raw"
    raise LabrigError(
        f"{path} is neither a Prophesee RAW file (no '% ' header) nor an HDF5 file; "
        "give a .raw (EVT 3.0 / 2.0) or a Metavision .hdf5"
    )


class _Source:
    """Chunks of events/triggers from a .raw or Metavision .hdf5, with a progress measure."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.kind = _sniff(path)
        self.fields: dict[str, str] = {}
        self.geometry: tuple[int, int] | None = None
        self.skipped_words = 0
        if self.kind == "raw":
            from labrig.devices.raw import RawFormatError, open_decoder

            try:
                header, fmt, geo, _ = open_decoder(path)
            except RawFormatError as exc:
                raise LabrigError(str(exc)) from None
            self.format = fmt
            self.fields = dict(header.fields)
            self.geometry = geo
            self.total = path.stat().st_size - header.size
            self.unit = "bytes"
        else:
            import h5py

            from labrig.devices.ecf import EcfError, _open_h5, geometry_from_attrs

            try:
                with h5py.File(path, "r") as f:
                    if f.attrs.get("schema") == "labrig.recording":
                        raise LabrigError(f"{path} is already a labrig recording; nothing to import")
            except OSError as exc:
                raise LabrigError(f"{path} is not a readable HDF5 file ({str(exc).splitlines()[0]})") from None
            try:
                with _open_h5(path) as f:
                    self.total = int(f["CD/events"].shape[0])
                    self.fields = {k: (v.decode() if isinstance(v, bytes) else str(v)) for k, v in f.attrs.items()}
            except EcfError as exc:
                raise LabrigError(str(exc)) from None
            self.format = "metavision-hdf5"
            self.geometry = geometry_from_attrs(self.fields)
            self.unit = "events"

    def chunks(self) -> Iterator[tuple[npt.NDArray[Any], npt.NDArray[Any], int]]:
        """(events, triggers, progress done) per chunk."""
        if self.kind == "raw":
            from labrig.devices.raw import open_decoder

            header, _, _, decoder = open_decoder(self.path)
            done = 0
            with open(self.path, "rb") as f:
                f.seek(header.size)
                while data := f.read(IMPORT_READ_BYTES):
                    out = decoder.feed(data)
                    done += len(data)
                    yield out.events, out.triggers, done
            decoder.finish()
            self.skipped_words = decoder.skipped_words
            return
        from labrig.devices.ecf import EcfError, iter_metavision_chunks
        from labrig.devices.raw import TRIGGER_DTYPE
        from labrig.eventtypes import EVENT_DTYPE

        done = 0
        try:
            for events in iter_metavision_chunks(self.path):
                done += events.size
                yield events, np.zeros(0, TRIGGER_DTYPE), done
        except EcfError as exc:
            raise LabrigError(str(exc)) from None
        triggers = _metavision_triggers(self.path)
        if triggers.size:
            yield np.zeros(0, EVENT_DTYPE), triggers, done


def _metavision_triggers(path: Path) -> npt.NDArray[Any]:
    """``/EXT_TRIGGER/events`` (stored uncompressed) as TRIGGER_DTYPE; empty when the file has none."""
    import h5py

    from labrig.devices.raw import TRIGGER_DTYPE

    with h5py.File(path, "r") as f:
        if "EXT_TRIGGER" not in f or "events" not in f["EXT_TRIGGER"]:
            return np.zeros(0, TRIGGER_DTYPE)
        raw = f["EXT_TRIGGER/events"][:]
    out = np.empty(raw.size, TRIGGER_DTYPE)
    out["p"], out["t"], out["id"] = raw["p"], raw["t"], raw["id"]
    return out


def import_file(source: Path, output: Path, *, overwrite: bool = False, progress: bool = True) -> dict[str, Any]:
    """Convert ``source`` (.raw EVT3/EVT2 or Metavision .hdf5) into the labrig recording ``output``."""
    from labrig.recording import RecordingMetadata, RecordingWriter

    src = _Source(source)
    if output.exists() and not overwrite:
        raise LabrigError(f"{output} exists; choose another name or pass --overwrite")
    if output.resolve() == source.resolve():
        raise LabrigError("the output must not be the source file")
    width, height = src.geometry or (1280, 720)
    extra: dict[str, str | int | float | bool] = {
        "source_file": str(source),
        "source_format": src.format,
        "source_serial": src.fields.get("serial_number", ""),
        "camera_width": int(width),
        "camera_height": int(height),
        "host_time": "none in the source: t_host_us = device time since the first event",
    }
    for key in ("date", "plugin_name", "sensor_generation", "system_ID"):
        if key in src.fields:
            extra[f"source_{key}"] = src.fields[key]
    t_start = time.perf_counter()
    n_events = n_triggers = 0
    t_first: int | None = None
    t_last = 0
    writer = RecordingWriter(output, RecordingMetadata(extra=extra), overwrite=overwrite)
    with _progress(not progress) as bar, writer:
        task = bar.add_task(f"import {source.name}", total=src.total, unit=src.unit)
        for events, triggers, done in src.chunks():
            if events.size:
                if t_first is None:
                    t_first = int(events["t"][0])
                t_last = max(t_last, int(events["t"].max()))
                for a in range(0, events.size, 1 << 16):
                    part = events[a : a + (1 << 16)]
                    host = int(part["t"][-1]) - t_first
                    while n_events - writer.stats["events"].rows_written > MAX_IN_FLIGHT_EVENTS:
                        if writer.fault:
                            break
                        time.sleep(0.002)
                    while not writer.put_events(part["x"], part["y"], part["p"], part["t"], max(host, 0)):
                        if writer.fault:
                            raise LabrigError(f"writing {output} failed: {writer.fault}")
                        time.sleep(0.01)  # queue full: wait for the writer thread
                    n_events += part.size
            if triggers.size:
                while not writer.put("triggers", t_device_us=triggers["t"], polarity=triggers["p"], channel=triggers["id"]):
                    if writer.fault:
                        raise LabrigError(f"writing {output} failed: {writer.fault}")
                    time.sleep(0.01)
                n_triggers += triggers.size
            bar.update(task, completed=done)
    result = writer.result
    elapsed = time.perf_counter() - t_start
    dropped = sum(result.dropped.values()) if result is not None else 0
    if dropped:
        raise LabrigError(f"{dropped} rows could not be written to {output} (see its drops stream)")
    return {
        "source": str(source),
        "source_format": src.format,
        "output": str(output),
        "events": n_events,
        "triggers": n_triggers,
        "t_first_device_us": t_first if t_first is not None else -1,
        "t_last_device_us": t_last if t_first is not None else -1,
        "duration_s": (t_last - t_first) / 1e6 if t_first is not None else 0.0,
        "width_px": int(width),
        "height_px": int(height),
        "skipped_words": src.skipped_words,
        "output_bytes": output.stat().st_size,
        "elapsed_s": elapsed,
    }


# -- export ------------------------------------------------------------------------------------


def export_raw(recording: Path, output: Path, *, overwrite: bool = False, progress: bool = True) -> dict[str, Any]:
    """Write the events and trigger edges of ``recording`` as an EVK4-like EVT 3.0 RAW file."""
    from labrig.devices.raw import TRIGGER_DTYPE, make_header
    from labrig.eventtypes import EVENT_DTYPE
    from labrig.recording import Recording
    from labrig.sim.evk4_twin import Evt3StreamEncoder

    if not recording.exists():
        raise LabrigError(f"{recording}: no such file")
    if output.exists() and not overwrite:
        raise LabrigError(f"{output} exists; choose another name or pass --overwrite")
    t_start = time.perf_counter()
    with Recording(recording) as rec:
        attrs = rec.attrs
        n = rec.rows("events")
        x_max = y_max = 0
        for a in range(0, n, EXPORT_SLICE_EVENTS):
            x_max = max(x_max, int(rec.column("events", "x", a, a + EXPORT_SLICE_EVENTS).max()))
            y_max = max(y_max, int(rec.column("events", "y", a, a + EXPORT_SLICE_EVENTS).max()))
        width = int(attrs.get("extra_camera_width", 1280))
        height = int(attrs.get("extra_camera_height", 720))
        if x_max >= width or y_max >= height:
            raise LabrigError(f"{recording}: events reach ({x_max}, {y_max}), outside the {width}x{height} sensor it names")
        tr_rows = rec.stream("triggers")
        triggers = np.zeros(tr_rows["t_device_us"].size, TRIGGER_DTYPE)
        triggers["t"], triggers["p"], triggers["id"] = tr_rows["t_device_us"], tr_rows["polarity"], tr_rows["channel"]
        if np.any(triggers["id"] > 15):
            raise LabrigError("EVT 3.0 carries trigger channels 0..15 only")
        triggers = triggers[np.argsort(triggers["t"], kind="stable")]
        fields = {"serial_number": str(attrs.get("extra_source_serial", "") or "00000000")}
        encoder = Evt3StreamEncoder(width, height)
        tmp = Path(os.fspath(output) + ".partial")
        size = 0
        try:
            with _progress(not progress) as bar, open(tmp, "wb") as f:
                task = bar.add_task(f"export {recording.name}", total=n, unit="events")
                size += f.write(make_header("EVT3", width, height, fields))
                k = 0
                for a in range(0, max(n, 1), EXPORT_SLICE_EVENTS):
                    b = min(a + EXPORT_SLICE_EVENTS, n)
                    ev = np.zeros(b - a, EVENT_DTYPE)
                    for name, col in (("x", "x"), ("y", "y"), ("p", "p"), ("t", "t_device_us")):
                        ev[name] = rec.column("events", col, a, b)
                    last = b >= n
                    k_end = triggers.size if last else int(np.searchsorted(triggers["t"], int(ev["t"][-1]), side="right"))
                    try:
                        size += f.write(encoder.encode(ev, triggers[k:k_end]))
                    except ValueError as exc:
                        raise LabrigError(f"{recording}: cannot be written as EVT 3.0: {exc}") from None
                    k = max(k, k_end)
                    bar.update(task, completed=b)
            os.replace(tmp, output)
        finally:
            if tmp.exists():
                tmp.unlink()
    return {
        "recording": str(recording),
        "output": str(output),
        "format": "EVT3",
        "events": n,
        "triggers": int(triggers.size),
        "width_px": width,
        "height_px": height,
        "output_bytes": size,
        "bytes_per_event": size / n if n else 0.0,
        "elapsed_s": time.perf_counter() - t_start,
    }


# -- commands -----------------------------------------------------------------------------------


def import_command(
    file: Annotated[Path, typer.Argument(help="Prophesee RAW (.raw, EVT 3.0 / 2.0) or Metavision HDF5 (.hdf5).")],
    output: Annotated[Path, typer.Argument(help="labrig recording to write (.h5).")],
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Import a camera file into a labrig recording (events, trigger edges, source metadata)."""
    summary = import_file(file, output, overwrite=overwrite, progress=not as_json)
    if as_json:
        _print_json(summary)
        return
    rate = summary["events"] / summary["elapsed_s"] / 1e6 if summary["elapsed_s"] > 0 else 0.0
    console.print(
        f"[green]imported[/] {summary['events']:,} events and {summary['triggers']} trigger edges "
        f"({summary['duration_s']:.3f} s of {summary['source_format']}) into {output} "
        f"in {summary['elapsed_s']:.2f} s ({rate:.1f} Mev/s)",
        highlight=False,
    )
    if summary["skipped_words"]:
        console.print(f"[yellow]warning:[/] {summary['skipped_words']} words of the RAW payload were not decoded")


def export_command(
    recording: Annotated[Path, typer.Argument(help="labrig recording (.h5).")],
    raw: Annotated[Path, typer.Option("--raw", help="Write the events as an EVT 3.0 RAW file here.")],
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Export a recording's camera events and trigger edges as an EVT 3.0 .raw (readable by Prophesee tools)."""
    summary = export_raw(recording, raw, overwrite=overwrite, progress=not as_json)
    if as_json:
        _print_json(summary)
        return
    console.print(
        f"[green]exported[/] {summary['events']:,} events and {summary['triggers']} trigger edges to {raw} "
        f"({summary['output_bytes'] / 1e6:.1f} MB, {summary['bytes_per_event']:.2f} B/event)",
        highlight=False,
    )


def add_camera_commands(app: typer.Typer) -> None:
    """Mount ``import`` and ``export`` on the main app."""
    app.command("import")(import_command)
    app.command("export")(export_command)
