"""Recording format v1: the streams a recording holds and how they are stored.

A stream is a table of columns that grow together, one HDF5 dataset per column
under ``/streams/<name>/``. The full layout, units and rules for readers are in
docs/recording-format.md; this module is the single source of truth for it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SCHEMA_NAME = "labrig.recording"
SCHEMA_VERSION = "1.0"
SCHEMA_MAJOR = 1

EXIT_RECORDING = "recording"
EXIT_COMPLETE = "complete"
EXIT_ABORTED = "aborted"
EXIT_RECOVERED = "crashed-recovered"
EXIT_STATUSES = (EXIT_COMPLETE, EXIT_ABORTED, EXIT_RECOVERED)

#: Width of the event time index bins, device microseconds.
EVENT_INDEX_BIN_US = 1000


@dataclass(frozen=True)
class Column:
    """One column: per-row dtype and shape, unit and meaning."""

    name: str
    dtype: str
    unit: str
    description: str
    shape: tuple[int, ...] = ()

    @property
    def np_dtype(self) -> np.dtype:
        return np.dtype(self.dtype)


@dataclass(frozen=True)
class StreamSpec:
    """A table of columns appended together.

    ``clock``: the device whose clock model maps this stream's ``t_device_us``
    to the host time base (``None``: the stream is stamped on the host clock).
    ``bulk``: the stream is large (camera events) and uses the recording's bulk
    codec; other streams use gzip so that any HDF5 reader can open them.
    ``codec``: a codec of its own (a name in :data:`labrig.recording.codecs.CODECS`),
    overriding both (the sim's large truth streams).
    """

    name: str
    columns: tuple[Column, ...]
    chunk_rows: int
    description: str
    clock: str | None = None
    bulk: bool = False
    attrs: dict[str, object] = field(default_factory=dict)
    codec: str | None = None

    def column(self, name: str) -> Column:
        for c in self.columns:
            if c.name == name:
                return c
        raise KeyError(f"stream {self.name!r} has no column {name!r}")

    @property
    def column_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.columns)


def _c(name: str, dtype: str, unit: str, description: str, shape: tuple[int, ...] = ()) -> Column:
    return Column(name, dtype, unit, description, shape)


EVENTS = StreamSpec(
    "events",
    (
        _c("x", "<u2", "px", "sensor column"),
        _c("y", "<u2", "px", "sensor row"),
        _c("p", "u1", "", "polarity: 1 ON (brighter), 0 OFF"),
        _c("t_device_us", "<i8", "us", "sensor time, unwrapped, as decoded"),
    ),
    chunk_rows=1 << 15,
    description="camera change-detection events",
    clock="camera",
    bulk=True,
)
EVENT_PACKETS = StreamSpec(
    "event_packets",
    (
        _c("end_row", "<i8", "", "number of events received up to and including this packet"),
        _c("t_device_us", "<i8", "us", "sensor time of the packet's last event"),
        _c("t_host_us", "<i8", "us", "host receive time"),
    ),
    chunk_rows=4096,
    description="host receive time of each camera packet (clock pairs for the camera)",
    clock="camera",
)
TRIGGERS = StreamSpec(
    "triggers",
    (
        _c("t_device_us", "<i8", "us", "sensor time of the edge"),
        _c("polarity", "u1", "", "1 rising, 0 falling"),
        _c("channel", "u1", "", "trigger input channel"),
    ),
    chunk_rows=1024,
    description="external trigger edges seen by the camera",
    clock="camera",
)
TRIGGER_OUT = StreamSpec(
    "trigger_out",
    (
        _c("t_host_us", "<i8", "us", "host time of the edge, as known by the device that made it: the earliest it "
                                    "can have happened"),
        _c("polarity", "u1", "", "1 rising, 0 falling"),
        _c("t_latest_host_us", "<i8", "us", "the latest host time the edge can have happened (e.g. its device's "
                                           "answer received); int64 max: not known"),
    ),
    chunk_rows=1024,
    description="trigger edges sent to the camera (for hardware sync)",
)
FT = StreamSpec(
    "ft",
    (
        _c("t_device_us", "<u4", "us", "sensor timestamp, raw uint32 (wraps every 2**32 us)"),
        _c("t_host_us", "<i8", "us", "host receive time"),
        _c("force_n", "<f4", "N", "Fx, Fy, Fz in the sensor frame", (3,)),
        _c("torque_nm", "<f4", "N m", "Tx, Ty, Tz in the sensor frame", (3,)),
        _c("status", "<u2", "", "sensor status bits"),
        _c("temperature_c", "<f4", "degC", "sensor temperature"),
    ),
    chunk_rows=8192,
    description="six-axis force-torque samples",
    clock="ft",
    attrs={"t_device_wrap_bits": 32},
)
CNC = StreamSpec(
    "cnc",
    (
        _c("t_host_us", "<i8", "us", "host receive time of the status report"),
        _c("position_mm", "<f8", "mm", "machine position X, Y, Z", (3,)),
        _c("feed_mm_min", "<f4", "mm/min", "current feed rate"),
        _c("state", "S16", "", "controller state (Idle, Run, Hold:0, Alarm, ...)"),
    ),
    chunk_rows=1024,
    description="CNC status samples",
)
GCODE = StreamSpec(
    "gcode",
    (
        _c("t_host_us", "<i8", "us", "host time the line was sent or received"),
        _c("direction", "u1", "", "0 sent to the controller, 1 received from it"),
        _c("line", "S128", "", "the line, without its terminator"),
    ),
    chunk_rows=1024,
    description="G-code command log",
)
PHASES = StreamSpec(
    "phases",
    (
        _c("name", "S32", "", "protocol phase"),
        _c("t_start_us", "<i8", "us", "host time the phase began"),
        _c("t_end_us", "<i8", "us", "host time the phase ended; -1 while open"),
    ),
    chunk_rows=64,
    description="protocol phases as intervals",
)
DROPS = StreamSpec(
    "drops",
    (
        _c("t_host_us", "<i8", "us", "host time of the drop"),
        _c("stream", "S32", "", "stream whose data was dropped"),
        _c("rows", "<i8", "", "rows dropped"),
        _c("reason", "S32", "", "queue-full, disk-full, ..."),
    ),
    chunk_rows=256,
    description="data the recorder could not keep, with why",
)

#: Streams every recording has, in file order.
CORE_STREAMS: tuple[StreamSpec, ...] = (EVENTS, EVENT_PACKETS, TRIGGERS, TRIGGER_OUT, FT, CNC, GCODE, PHASES, DROPS)

#: The commits table: row counts of every stream after each complete flush.
COMMITS_PATH = "recording/commits"

#: Devices with a stored clock model, and the stream that gives their pairs.
CLOCK_SOURCES = {"camera": "event_packets", "ft": "ft"}
