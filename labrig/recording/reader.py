"""Reading recordings: metadata, streams, clock-mapped times, fast event slicing.

Times returned by the reader are in the recording's host time base (``t_us``,
host microseconds since the recording's start), mapped from device time with
the clock model stored at finalization. A file that was never finalized (a
crash) is read through SWMR, trusting only rows up to its last commit, with
clock models fitted on the fly.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import hdf5plugin  # noqa: F401  (registers the bulk codecs' HDF5 filters)
import numpy as np
import numpy.typing as npt

from labrig.clock import ClockModel, unwrap_counter
from labrig.errors import RecordingError
from labrig.eventtypes import EVENT_DTYPE
from labrig.recording import schema
from labrig.recording.finalize import committed_rows, fit_clock_models
from labrig.recording.layout import stream_group, stream_path

#: Rows of each event column read at once and kept for the windows that follow (x, y, p, t: 13 bytes a row).
EVENT_READ_AHEAD_ROWS = 1 << 18


@dataclass(frozen=True)
class Phase:
    name: str
    t_start_us: int
    t_end_us: int

    @property
    def duration_s(self) -> float:
        return (self.t_end_us - self.t_start_us) / 1e6


def open_h5(path: str | os.PathLike[str]) -> h5py.File:
    """Open an HDF5 file read-only, with one-line errors for every bad case.

    A file still marked as open by a crashed SWMR writer is opened in SWMR
    read mode, which is valid by construction.
    """
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: no such file; check the path")
    if p.is_dir():
        raise RecordingError(f"{p} is a directory; give a recording file (.h5)")
    if p.stat().st_size == 0:
        raise RecordingError(f"{p} is empty (0 bytes); it is not a recording")
    if not h5py.is_hdf5(p):
        raise RecordingError(f"{p} is not an HDF5 file (or is truncated before its superblock); give a labrig recording")
    try:
        return h5py.File(p, "r")
    except OSError as exc:
        if "already open for write" in str(exc):
            try:
                return h5py.File(p, "r", swmr=True)
            except OSError as exc2:
                raise RecordingError(f"{p} cannot be opened: {_first_line(exc2)}") from None
        hint = f"; run `labrig recover {p}`" if p.name.endswith(".partial") else "; it cannot be read"
        message = f"{p} is truncated or damaged ({_first_line(exc)}){hint}"
        short = re.search(r"truncated file: eof = (\d+).*stored_eof = (\d+)", str(exc))
        if short:
            raise TruncatedRecording(message, int(short[1]), int(short[2])) from None
        raise RecordingError(message) from None


class TruncatedRecording(RecordingError):
    """The file ends before where its superblock says (a write failed mid-flush)."""

    def __init__(self, message: str, eof: int, stored_eof: int) -> None:
        super().__init__(message)
        self.eof = eof
        self.stored_eof = stored_eof


def _first_line(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


class Recording:
    """A recording file, open for reading. Use as a context manager."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.file = open_h5(self.path)
        try:
            self._check_schema()
            self.finalized = bool(self.file.attrs.get("finalized", False))
            self._rows = self._row_counts()
            self._clock_models = self._load_clock_models()
        except (KeyError, OSError, ValueError) as exc:
            self.file.close()
            raise RecordingError(f"{self.path} is damaged ({_first_line(exc)}); run `labrig recover {self.path}`") from None
        except RecordingError:
            self.file.close()
            raise
        self._event_index: tuple[int, npt.NDArray[np.int64]] | None = None
        self._event_bin_us: int | None = None
        # Read-ahead of the event columns: (first row, (x, y, p, t_device_us)); windows read in order hit it.
        self._event_block: tuple[int, tuple[npt.NDArray[Any], ...]] | None = None

    def _check_schema(self) -> None:
        attrs = self.file.attrs
        if attrs.get("schema") != schema.SCHEMA_NAME:
            raise RecordingError(f"{self.path} is an HDF5 file but not a labrig recording (no schema={schema.SCHEMA_NAME!r})")
        version = str(attrs.get("schema_version", ""))
        try:
            major = int(version.split(".")[0])
        except ValueError:
            raise RecordingError(f"{self.path} has an unreadable schema_version {version!r}") from None
        if major > schema.SCHEMA_MAJOR:
            raise RecordingError(
                f"{self.path} uses recording format {version}, newer than this labrig reads "
                f"({schema.SCHEMA_VERSION}); upgrade labrig"
            )

    def _row_counts(self) -> dict[str, int]:
        commits = None if self.finalized else committed_rows(self.file)
        rows: dict[str, int] = {}
        for name in self.file[schema.COMMITS_PATH].attrs["streams"]:
            group = self.file[stream_path(name)]
            spec_columns = [k for k in group if isinstance(group[k], h5py.Dataset) and not k.startswith("index_")]
            n = min(group[k].shape[0] for k in spec_columns)
            if not self.finalized:
                n = min(n, (commits or {}).get(name, 0))
            rows[name] = n
        return rows

    def _load_clock_models(self) -> dict[str, ClockModel]:
        if self.finalized:
            return {d: ClockModel.from_attrs(dict(g.attrs)) for d, g in self.file["clock"].items() if "method" in g.attrs}
        return fit_clock_models(self.file, self._rows)

    # -- metadata ------------------------------------------------------------

    def close(self) -> None:
        self.file.close()

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def attrs(self) -> dict[str, Any]:
        return {k: _plain(v) for k, v in self.file.attrs.items()}

    @property
    def exit_status(self) -> str:
        return str(self.file.attrs.get("exit_status", "unknown"))

    @property
    def exit_reason(self) -> str:
        """Why an aborted recording stopped ("" when complete)."""
        return str(self.file.attrs.get("exit_reason", ""))

    @property
    def streams(self) -> tuple[str, ...]:
        return tuple(self._rows)

    def rows(self, stream: str) -> int:
        return self._rows[stream]

    def clock_model(self, device: str) -> ClockModel:
        """The stored final model (identity if the device never sent pairs)."""
        return self._clock_models.get(device, ClockModel())

    @property
    def clock_models(self) -> dict[str, ClockModel]:
        return dict(self._clock_models)

    # -- streams -------------------------------------------------------------

    def column(self, stream: str, name: str, start: int = 0, stop: int | None = None) -> npt.NDArray[Any]:
        n = self._rows[stream]
        stop = n if stop is None else min(stop, n)
        return stream_group(self.file, stream)[name][start:stop]

    def stream(self, stream: str) -> dict[str, npt.NDArray[Any]]:
        group = stream_group(self.file, stream)
        return {k: self.column(stream, k) for k in group if k in self._columns(stream)}

    def _columns(self, stream: str) -> list[str]:
        group = stream_group(self.file, stream)
        return [k for k in group if isinstance(group[k], h5py.Dataset) and not k.startswith("index_")]

    def ft(self) -> dict[str, npt.NDArray[Any]]:
        """F/T samples with ``t_us`` mapped from the sensor clock."""
        data = self.stream("ft")
        device_us = unwrap_counter(data["t_device_us"], 32)
        data["t_us"] = self.clock_model("ft").to_host_us_int(device_us)
        return data

    def phases(self) -> list[Phase]:
        data = self.stream("phases")
        end_us = self.end_us()
        return [
            Phase(n.decode(), int(s), int(e) if e >= 0 else end_us)
            for n, s, e in zip(data["name"], data["t_start_us"], data["t_end_us"])
        ]

    def end_us(self) -> int:
        """Latest host time any stream reached."""
        ends = [0]
        for stream, column in (("cnc", "t_host_us"), ("ft", "t_host_us"), ("event_packets", "t_host_us"), ("gcode", "t_host_us")):
            if self._rows[stream]:
                ends.append(int(self.column(stream, column, self._rows[stream] - 1)[0]))
        return max(ends)

    # -- events --------------------------------------------------------------

    @property
    def n_events(self) -> int:
        return self._rows["events"]

    def events_end_us(self) -> int | None:
        """Host time (us) of the newest event (None without events): where the camera stream stops."""
        n = self.n_events
        if n == 0:
            return None
        tail = self.column("events", "t_device_us", max(0, n - 4096), n)  # device times may step back a little
        return int(self.clock_model("camera").to_host_us_int(tail.max()))

    def event_index(self) -> tuple[int, npt.NDArray[np.int64]]:
        """(start_bin, first_row per bin) of the event time index, cached."""
        if self._event_index is None:
            group = self.file["streams/events"]
            start_bin = int(group["index_start_bin"][0])
            first_row = np.minimum(group["index_first_row"][:], self.n_events)
            self._event_index = (start_bin, first_row)
        return self._event_index

    def events_between(self, t0_us: float, t1_us: float) -> npt.NDArray[Any]:
        """Events with host time in ``[t0_us, t1_us)``; ``t`` in the host base (us).

        The time index narrows the read to the bins that can hold the window,
        so slicing costs O(window), not O(recording).
        """
        model = self.clock_model("camera")
        d0, d1 = model.to_device_us([t0_us, t1_us])
        x, y, p, t_dev = self._device_window(int(np.floor(d0)), int(np.ceil(d1)))
        t = model.to_host_us_int(t_dev)
        keep = (t >= t0_us) & (t < t1_us)
        out = np.empty(int(keep.sum()), dtype=EVENT_DTYPE)
        out["x"], out["y"], out["p"], out["t"] = x[keep], y[keep], p[keep], t[keep]
        return out

    def _device_window(self, d0_us: int, d1_us: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        start_bin, first_row = self.event_index()
        if start_bin < 0 or first_row.size == 0:
            empty = np.zeros(0, np.int64)
            return empty, empty, empty, empty
        if self._event_bin_us is None:
            self._event_bin_us = int(self.file["streams/events"].attrs["index_bin_us"])
        bin_us = self._event_bin_us
        k0 = d0_us // bin_us - start_bin
        # One extra bin past the end covers timestamps that step backwards.
        k1 = -(-d1_us // bin_us) - start_bin + 1
        i0 = int(first_row[k0]) if 0 <= k0 < first_row.size else (0 if k0 < 0 else self.n_events)
        i1 = int(first_row[k1]) if 0 <= k1 < first_row.size else (0 if k1 < 0 else self.n_events)
        if i1 <= i0:
            empty = np.zeros(0, np.int64)
            return empty, empty, empty, empty
        x, y, p, t = self._event_rows(i0, i1)
        return x, y, p, t

    def _event_rows(self, i0: int, i1: int) -> tuple[npt.NDArray[Any], ...]:
        """The event columns (x, y, p, t_device_us) of rows ``[i0, i1)``, through a read-ahead block of at
        least ``EVENT_READ_AHEAD_ROWS`` rows: one HDF5 read per column serves the windows that follow
        (a 10 ms window is a few thousand rows; four small reads a window cost about 1 ms in h5py's
        per-call overhead and chunk decompression)."""
        block = self._event_block
        if block is None or i0 < block[0] or i1 > block[0] + len(block[1][0]):
            stop = min(max(i1, i0 + EVENT_READ_AHEAD_ROWS), self.n_events)
            block = (i0, tuple(self.column("events", c, i0, stop) for c in ("x", "y", "p", "t_device_us")))
            self._event_block = block
        a, b = i0 - block[0], i1 - block[0]
        return tuple(column[a:b] for column in block[1])

    def event_counts(self, bin_ms: float = 10.0) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
        """Event counts per ``bin_ms`` from the index alone: (bin start t_us, counts)."""
        start_bin, first_row = self.event_index()
        if start_bin < 0 or first_row.size == 0:
            return np.zeros(0), np.zeros(0, np.int64)
        bin_us = int(self.file["streams/events"].attrs["index_bin_us"])
        step = max(1, round(bin_ms * 1000 / bin_us))
        edges = np.append(first_row[::step], self.n_events)
        counts = np.diff(edges)
        device_start = (start_bin + np.arange(counts.size) * step) * bin_us
        return self.clock_model("camera").to_host_us(device_start), counts


def _plain(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()]
    return value
