"""Camera files to and from labrig recordings: Prophesee RAW (EVT 3.0 / 2.0) or Metavision HDF5 in
(:func:`import_file`, ``labrig import``), an EVK4-like EVT 3.0 RAW out (:func:`export_raw`, ``labrig export``).

An imported file has no host clock: the recording's host times (``t_host_us`` of the event
packets) are the device times counted from the first event, so the stored camera clock model
is the identity plus an offset. The recording's ``extra_source_*`` attributes name the source.

Both report progress through an optional callback ``progress(done, total, unit)`` (``unit``:
``bytes`` or ``events``), called once with ``done = 0`` before the first chunk.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.devices.ecf import (
    EcfError,
    geometry_from_attrs,
    iter_metavision_chunks,
    metavision_attrs,
    metavision_event_count,
    metavision_triggers,
)
from labrig.devices.raw import TRIGGER_DTYPE, Evt3StreamEncoder, RawFormatError, make_header, open_decoder
from labrig.errors import LabrigError
from labrig.eventtypes import EVENT_DTYPE
from labrig.recording.reader import Recording
from labrig.recording.writer import RecordingMetadata, RecordingWriter

#: ``progress(done, total, unit)``: how far a conversion is.
ConversionProgress = Callable[[int, int, str], None]

HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
#: Events put into the recording writer but not yet written, at most (backpressure on import).
MAX_IN_FLIGHT_EVENTS = 1 << 22
#: Events per slice when reading a recording for export.
EXPORT_SLICE_EVENTS = 1 << 20
#: Payload bytes per read when importing a RAW file.
IMPORT_READ_BYTES = 16 << 20


def _no_progress(done: int, total: int, unit: str) -> None:
    pass


# -- import ------------------------------------------------------------------------------------


def sniff_camera_file(path: Path) -> str:
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
        self.kind = sniff_camera_file(path)
        self.fields: dict[str, str] = {}
        self.geometry: tuple[int, int] | None = None
        self.skipped_words = 0
        if self.kind == "raw":
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

            try:
                with h5py.File(path, "r") as f:
                    if f.attrs.get("schema") == "labrig.recording":
                        raise LabrigError(f"{path} is already a labrig recording; nothing to import")
            except OSError as exc:
                raise LabrigError(f"{path} is not a readable HDF5 file ({str(exc).splitlines()[0]})") from None
            try:
                self.total = metavision_event_count(path)
                self.fields = metavision_attrs(path)
            except EcfError as exc:
                raise LabrigError(str(exc)) from None
            self.format = "metavision-hdf5"
            self.geometry = geometry_from_attrs(self.fields)
            self.unit = "events"

    def chunks(self) -> Iterator[tuple[npt.NDArray[Any], npt.NDArray[Any], int]]:
        """(events, triggers, progress done) per chunk."""
        if self.kind == "raw":
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

        done = 0
        try:
            for events in iter_metavision_chunks(self.path):
                done += events.size
                yield events, np.zeros(0, TRIGGER_DTYPE), done
        except EcfError as exc:
            raise LabrigError(str(exc)) from None
        triggers = metavision_triggers(self.path)
        if triggers.size:
            yield np.zeros(0, EVENT_DTYPE), triggers, done


@dataclass(frozen=True)
class ImportSummary:
    """What :func:`import_file` wrote: counts, the events' device-time span (us; -1 without events), sizes."""

    source: str
    source_format: str
    output: str
    events: int
    triggers: int
    t_first_device_us: int
    t_last_device_us: int
    duration_s: float
    width_px: int
    height_px: int
    skipped_words: int
    output_bytes: int
    elapsed_s: float


def import_file(source: Path, output: Path, *, overwrite: bool = False,
                progress: ConversionProgress | None = None) -> ImportSummary:
    """Convert ``source`` (.raw EVT3/EVT2 or Metavision .hdf5) into the labrig recording ``output``."""
    src = _Source(source)
    if output.exists() and not overwrite:
        raise LabrigError(f"{output} exists; choose another name or pass --overwrite")
    if output.resolve() == source.resolve():
        raise LabrigError("the output must not be the source file")
    report = progress or _no_progress
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
    with writer:
        report(0, src.total, src.unit)
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
            report(done, src.total, src.unit)
    result = writer.result
    elapsed = time.perf_counter() - t_start
    dropped = sum(result.dropped.values()) if result is not None else 0
    if dropped:
        raise LabrigError(f"{dropped} rows could not be written to {output} (see its drops stream)")
    return ImportSummary(
        source=str(source),
        source_format=src.format,
        output=str(output),
        events=n_events,
        triggers=n_triggers,
        t_first_device_us=t_first if t_first is not None else -1,
        t_last_device_us=t_last if t_first is not None else -1,
        duration_s=(t_last - t_first) / 1e6 if t_first is not None else 0.0,
        width_px=int(width),
        height_px=int(height),
        skipped_words=src.skipped_words,
        output_bytes=output.stat().st_size,
        elapsed_s=elapsed,
    )


# -- export ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExportSummary:
    """What :func:`export_raw` wrote: counts, the sensor size it names, bytes."""

    recording: str
    output: str
    format: str
    events: int
    triggers: int
    width_px: int
    height_px: int
    output_bytes: int
    bytes_per_event: float
    elapsed_s: float


def export_raw(recording: Path, output: Path, *, overwrite: bool = False,
               progress: ConversionProgress | None = None) -> ExportSummary:
    """Write the events and trigger edges of ``recording`` as an EVK4-like EVT 3.0 RAW file."""
    if not recording.exists():
        raise LabrigError(f"{recording}: no such file")
    if output.exists() and not overwrite:
        raise LabrigError(f"{output} exists; choose another name or pass --overwrite")
    report = progress or _no_progress
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
            with open(tmp, "wb") as f:
                report(0, n, "events")
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
                    report(b, n, "events")
            os.replace(tmp, output)
        finally:
            if tmp.exists():
                tmp.unlink()
    return ExportSummary(
        recording=str(recording),
        output=str(output),
        format="EVT3",
        events=n,
        triggers=int(triggers.size),
        width_px=width,
        height_px=height,
        output_bytes=size,
        bytes_per_event=size / n if n else 0.0,
        elapsed_s=time.perf_counter() - t_start,
    )
