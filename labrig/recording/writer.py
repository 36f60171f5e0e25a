"""Crash-safe recording writer: producer threads, one HDF5 writer thread.

Producers (camera, F/T, CNC, protocol runner) call :meth:`RecordingWriter.put`
from their own threads; each stream has a bounded queue, and a full queue is
counted in the ``drops`` stream, never silently lost. One writer thread owns the
HDF5 file (h5py serialises all HDF5 calls anyway), coalesces batches into whole
chunks, and flushes at least every ``flush_interval_s``.

Crash safety:
* the file is written as ``NAME.partial`` in HDF5 SWMR mode, whose on-disk
  state is readable after a crash at any instant (kill -9 included);
* after every complete flush a row of per-stream row counts is appended to
  ``/recording/commits`` and flushed, so a reader trusts exactly the data that
  reached the disk, even when a write failed half-way (disk full);
* free disk space (and the process file-size limit) is checked before writing:
  when it runs low the recorder stops cleanly, keeps what it has and finalizes;
* finalization closes the file, stores the final clock models and the exit
  status, and renames ``NAME.partial`` to ``NAME`` atomically.
"""

from __future__ import annotations

import errno
import os
import queue
import resource
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import h5py
import numpy as np
import numpy.typing as npt

from labrig import __version__
from labrig.clock import NS_PER_US, ClockModel, CounterUnwrapper, HostClock, MonotonicClock
from labrig.clock_fit import OnlineClockFit
from labrig.errors import RecordingError, RecordingFault
from labrig.recording import schema
from labrig.recording.codecs import DEFAULT_BULK_CODEC, PORTABLE_CODEC, codec_kwargs
from labrig.recording.finalize import finalize_file
from labrig.recording.layout import create_layout, partial_path, stream_group
from labrig.recording.quality import Quality, store_quality

Columns = dict[str, npt.NDArray[Any]]

#: Chunks of a bulk stream gathered before writing them (at 10 Mev/s: ~26 ms).
BULK_WRITE_CHUNKS = 8
#: The writer thread looks at its queues at least this often, s.
POLL_S = 0.05

#: Files whose close failed after a write failure. HDF5 cannot shut down
#: cleanly with such a file open (it crashes at interpreter exit), so they are
#: kept referenced and :func:`exit_process` skips HDF5's shutdown.
_FAULTED_FILES: list[h5py.File] = []


def exit_process(code: int) -> NoReturn:
    """Exit with ``code``, skipping HDF5's shutdown if a write failure broke it.

    The data is safe on disk either way; this only avoids a crash at exit.
    """
    if _FAULTED_FILES:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


@dataclass
class RecordingMetadata:
    """What a recording says about itself (root attributes and /calibration).

    Text fields hold TOML documents exactly as loaded, so a recording is
    self-describing without labrig.
    """

    indenter: str = ""
    protocol_toml: str = ""
    rig_toml: str = ""
    gel_toml: str = ""
    #: The mounted indenter's own definition (:func:`labrig.indenters.indenter_toml`, height maps inline).
    indenter_toml: str = ""
    calibration: dict[str, str] = field(default_factory=dict)
    extra: dict[str, str | int | float | bool] = field(default_factory=dict)


@dataclass
class StreamStats:
    rows_written: int = 0
    rows_dropped: int = 0
    batches_dropped: int = 0


@dataclass(frozen=True)
class RecordingResult:
    """What a closed recording holds and where it is."""

    path: Path
    exit_status: str
    reason: str
    rows: dict[str, int]
    dropped: dict[str, int]
    fault: str = ""
    quality: Quality | None = None  # the data's verdict (labrig.recording.quality); None when not finalized


class _PhaseTable:
    """Protocol phases; the whole small table is rewritten at each flush."""

    def __init__(self) -> None:
        self.rows: list[tuple[bytes, int, int]] = []
        self.dirty = False

    def begin(self, name: str, t_us: int) -> None:
        self.end(t_us)
        self.rows.append((name.encode()[:32], t_us, -1))
        self.dirty = True

    def end(self, t_us: int) -> None:
        if self.rows and self.rows[-1][2] < 0:
            name, start, _ = self.rows[-1]
            self.rows[-1] = (name, start, t_us)
            self.dirty = True


class _EventIndex:
    """Row of the first event at or after each time bin, kept as events arrive.

    Bin ``k`` starts at device time ``(start_bin + k) * bin_us``. Using the
    running maximum of time keeps the index sorted when the sensor's timestamps
    step back by a few microseconds (merged event sources).
    """

    #: A batch that would add more bins than this has corrupt timestamps.
    MAX_NEW_BINS = 3_600_000

    def __init__(self, bin_us: int) -> None:
        self.bin_us = bin_us
        self.start_bin = -1
        self.n_bins = 0
        self.running_max = np.iinfo(np.int64).min

    def extend(self, t_device_us: npt.NDArray[np.int64], first_row: int) -> npt.NDArray[np.int64]:
        """Index entries completed by these events (their rows are absolute)."""
        if t_device_us.size == 0:
            return np.zeros(0, np.int64)
        running = np.maximum.accumulate(np.maximum(t_device_us, self.running_max))
        if self.start_bin < 0:
            self.start_bin = int(running[0] // self.bin_us)
        last_bin = int(running[-1] // self.bin_us) - self.start_bin
        if last_bin - self.n_bins > self.MAX_NEW_BINS:
            raise ValueError(f"event time jumps by {(last_bin - self.n_bins) * self.bin_us} us; timestamps are corrupt")
        self.running_max = int(running[-1])
        new_bins = np.arange(self.n_bins, last_bin + 1, dtype=np.int64)
        starts = (self.start_bin + new_bins) * self.bin_us
        rows = first_row + np.searchsorted(running, starts, side="left")
        self.n_bins = last_bin + 1
        return rows.astype(np.int64)


class RecordingWriter:
    """Write one recording from several producer threads.

    Use as a context manager, or call :meth:`open` and :meth:`close`.
    ``min_free_bytes``: stop cleanly when less than this (plus twice the data
    about to be written) is left on the disk or under the file-size limit;
    ``None`` disables the guard. ``on_commit`` is called from the writer thread
    with the per-stream row counts after each complete flush. ``wake_on_put``
    False: a put does not wake the writer thread, which takes the queued rows
    every ``POLL_S`` (or at once when a queue is half full); for producers
    that run ahead of real time (virtual-time recordings), whose thousands of
    puts would each cost a thread switch, more than the writes themselves.
    All ``t_host_us`` values are in the recording's time base: host
    microseconds since ``t0_host_ns`` (see :mod:`labrig.clock`).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        metadata: RecordingMetadata | None = None,
        *,
        clock: HostClock | None = None,
        bulk_codec: str = DEFAULT_BULK_CODEC,
        extra_streams: tuple[schema.StreamSpec, ...] = (),
        queue_batches: int = 4096,
        flush_interval_s: float = 0.5,
        min_free_bytes: int | None = 64 << 20,
        overwrite: bool = False,
        on_commit: Callable[[dict[str, int]], None] | None = None,
        wake_on_put: bool = True,
    ) -> None:
        self.path = Path(path)
        self.partial = partial_path(self.path)
        self.metadata = metadata or RecordingMetadata()
        self.clock = clock or MonotonicClock()
        self.bulk_codec = bulk_codec
        codec_kwargs(bulk_codec)  # fail early on an unknown codec
        self.specs = {s.name: s for s in schema.CORE_STREAMS + tuple(extra_streams)}
        self.flush_interval_s = flush_interval_s
        self.wake_on_put = wake_on_put
        self._wake_batches = max(1, queue_batches // 2)
        self.min_free_bytes = min_free_bytes
        self.on_commit = on_commit
        self.overwrite = overwrite
        self.t0_host_ns = 0
        self.stats = {name: StreamStats() for name in self.specs}
        self._queues = {name: queue.Queue[Columns](maxsize=queue_batches) for name in self.specs}
        self._drop_lock = threading.Lock()
        self._drops_pending: list[tuple[int, str, int, str]] = []
        self._phases = _PhaseTable()
        self._phase_queue: queue.SimpleQueue[tuple[str, str, int]] = queue.SimpleQueue()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._file: h5py.File | None = None
        self._fault: str = ""
        self._fault_reason: str = ""
        self._online = {"camera": OnlineClockFit(), "ft": OnlineClockFit()}
        self._ft_unwrap = CounterUnwrapper(32)
        self._event_index = _EventIndex(schema.EVENT_INDEX_BIN_US)
        self._closed = False
        self.result: RecordingResult | None = None
        self._datasets: dict[str, dict[str, h5py.Dataset]] = {}
        self._pending: dict[str, list[Columns]] = {name: [] for name in self.specs}
        self._pending_rows = dict.fromkeys(self.specs, 0)
        #: Rows gathered before a write: several chunks for bulk streams, so the
        #: fixed cost of a write is paid rarely (writes still happen at every flush).
        self._write_rows = {name: s.chunk_rows * (BULK_WRITE_CHUNKS if s.bulk else 1) for name, s in self.specs.items()}

    # -- lifecycle ---------------------------------------------------------

    def open(self) -> RecordingWriter:
        if self.path.exists() and not self.overwrite:
            raise RecordingError(f"{self.path} already exists; choose another name or pass overwrite")
        if self.partial.exists():
            raise RecordingError(
                f"{self.partial} exists from an unfinished recording; run `labrig recover {self.partial}` or delete it"
            )
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.t0_host_ns = self.clock.now_ns()
        try:
            self._file = h5py.File(self.partial, "w", libver="latest", rdcc_nbytes=32 << 20, rdcc_nslots=10007)
        except OSError as exc:
            raise RecordingError(f"cannot create {self.partial}: {exc}") from None
        create_layout(self._file, self.specs.values(), self._root_attrs(), self.metadata.calibration, self.bulk_codec)
        self._datasets = {
            name: {key: ds for key, ds in stream_group(self._file, name).items() if isinstance(ds, h5py.Dataset)}
            for name in self.specs
        }
        self._file.swmr_mode = True
        self._thread = threading.Thread(target=self._run, name=f"labrig-writer:{self.path.name}", daemon=True)
        self._thread.start()
        return self

    def __enter__(self) -> RecordingWriter:
        return self.open()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None:
        if self._closed:
            return
        if exc is None:
            self.result = self.close()
        else:
            reason = "interrupted by the user" if isinstance(exc, KeyboardInterrupt) else f"{type(exc).__name__}: {exc}"
            self.result = self.close(schema.EXIT_ABORTED, reason, raise_on_fault=False)

    def close(self, exit_status: str = schema.EXIT_COMPLETE, reason: str = "", *, raise_on_fault: bool = True,
              attrs: dict[str, str | int | float | bool] | None = None) -> RecordingResult:
        """Stop the writer thread, write what is queued, finalize (``attrs``: root attributes known only
        at the end, e.g. how far a stream fell behind) and rename.

        On a fault (disk full, write failure) the data already flushed stays in
        ``NAME.partial`` and :class:`RecordingFault` says how to recover it.
        """
        if self._closed:
            raise RecordingError(f"{self.path} is already closed")
        if exit_status not in (schema.EXIT_COMPLETE, schema.EXIT_ABORTED):
            raise ValueError(f"exit status must be complete or aborted, not {exit_status!r}")
        self._closed = True
        self._phase_queue.put(("end", "", self.host_us()))
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join()
        rows = {name: s.rows_written for name, s in self.stats.items()}
        dropped = {name: s.rows_dropped for name, s in self.stats.items() if s.rows_dropped}
        if self._fault:
            result = RecordingResult(self.partial, "crashed", self._fault_reason, rows, dropped, self._fault)
            if raise_on_fault:
                raise RecordingFault(self._fault)
            return result
        if self._fault_reason:  # stopped cleanly by the disk-space guard
            exit_status, reason = schema.EXIT_ABORTED, self._fault_reason
        finalize_file(self.partial, exit_status, reason, online_models=self.online_models(), attrs=attrs)
        quality = store_quality(self.partial)
        os.replace(self.partial, self.path)
        _fsync_dir(self.path.parent)
        return RecordingResult(self.path, exit_status, reason, rows, dropped, quality=quality)

    def abort(self, reason: str) -> RecordingResult:
        return self.close(schema.EXIT_ABORTED, reason)

    # -- producer API (any thread) -----------------------------------------

    def host_us(self) -> int:
        """Now, in the recording's time base (host microseconds since t0)."""
        return (self.clock.now_ns() - self.t0_host_ns) // NS_PER_US

    def put(self, stream: str, **columns: npt.ArrayLike) -> bool:
        """Queue rows for ``stream``; False if they had to be dropped (counted).

        Columns are copied, so producers may reuse their buffers. A single row
        may be given as scalars.
        """
        spec = self.specs.get(stream)
        if spec is None:
            raise KeyError(f"unknown stream {stream!r}")
        if set(columns) != set(spec.column_names):
            missing = set(spec.column_names) - set(columns)
            extra = set(columns) - set(spec.column_names)
            raise ValueError(f"stream {stream!r}: missing columns {sorted(missing)}, unknown columns {sorted(extra)}")
        batch = {c.name: _as_rows(columns[c.name], c) for c in spec.columns}
        n = {len(v) for v in batch.values()}
        if len(n) != 1:
            raise ValueError(f"stream {stream!r}: columns have different lengths {sorted(n)}")
        return self._enqueue(stream, batch, n.pop())

    def put_events(
        self,
        x: npt.ArrayLike,
        y: npt.ArrayLike,
        p: npt.ArrayLike,
        t_device_us: npt.ArrayLike,
        t_host_us: int,
    ) -> bool:
        """Queue one camera packet: its events and the host time it arrived."""
        batch = {c.name: _as_rows(v, c) for c, v in zip(schema.EVENTS.columns, (x, y, p, t_device_us))}
        n = {len(v) for v in batch.values()}
        if len(n) != 1:
            raise ValueError(f"event columns have different lengths {sorted(n)}")
        batch["_t_host_us"] = np.array([t_host_us], dtype=np.int64)
        return self._enqueue("events", batch, n.pop())

    def phase_begin(self, name: str, t_host_us: int | None = None) -> None:
        """Start a protocol phase (ending the open one)."""
        self._phase_queue.put(("begin", name, self.host_us() if t_host_us is None else t_host_us))
        self._wake.set()

    def phase_end(self, t_host_us: int | None = None) -> None:
        self._phase_queue.put(("end", "", self.host_us() if t_host_us is None else t_host_us))
        self._wake.set()

    def clock_model(self, device: str) -> ClockModel | None:
        """The live (online) clock model of ``camera`` or ``ft``."""
        return self._online[device].model

    def online_models(self) -> dict[str, ClockModel]:
        """The live models fitted on every pair received so far."""
        models = {d: fit.refit() for d, fit in self._online.items()}
        return {d: m for d, m in models.items() if m is not None}

    @property
    def fault(self) -> str:
        return self._fault

    def _enqueue(self, stream: str, batch: Columns, n_rows: int) -> bool:
        if self._stop.is_set() or self._fault_reason:
            self._count_drop(stream, n_rows, "stopped" if not self._fault_reason else "disk-full")
            return False
        q = self._queues[stream]
        try:
            q.put_nowait(batch)
        except queue.Full:
            self._count_drop(stream, n_rows, "queue-full")
            return False
        if self.wake_on_put or q.qsize() >= self._wake_batches:
            self._wake.set()
        return True

    def _count_drop(self, stream: str, rows: int, reason: str) -> None:
        with self._drop_lock:
            st = self.stats[stream]
            st.rows_dropped += rows
            st.batches_dropped += 1
            self._drops_pending.append((self.host_us(), stream, rows, reason))

    # -- writer thread -----------------------------------------------------

    def _run(self) -> None:
        next_flush = time.monotonic() + self.flush_interval_s
        try:
            while True:
                if not self._stop.is_set():  # once stopping, write what is left at once
                    self._wake.wait(timeout=max(0.0, min(POLL_S, next_flush - time.monotonic())))
                self._wake.clear()
                stopping = self._stop.is_set()  # read before draining: what was put before the stop is queued
                for name, q in self._queues.items():
                    # Take only what is queued now (round robin, so a busy camera
                    # cannot starve the F/T stream); pending is written as it
                    # reaches a write's worth, so memory stays bounded.
                    for _ in range(q.qsize()):
                        try:
                            batch = q.get_nowait()
                        except queue.Empty:
                            break
                        self._add_pending(name, batch)
                if stopping or self._fault_reason or time.monotonic() >= next_flush:
                    for name in self.specs:
                        self._write_pending(name)
                    self._apply_phases()
                    self._flush_and_commit()
                    next_flush = time.monotonic() + self.flush_interval_s
                if stopping or self._fault_reason:
                    break
        except Exception as exc:  # a write failed: keep what reached the disk
            self._fault_reason = _describe_write_failure(exc)
            self._fault = (
                f"recording stopped: {self._fault_reason}. Data up to the last flush is kept in {self.partial}; "
                f"fix the cause, then run `labrig recover {self.partial}`"
            )
            self._stop.set()
            try:
                assert self._file is not None
                self._file.close()
            except Exception:
                _FAULTED_FILES.append(self._file)
            return
        assert self._file is not None
        self._file.close()

    def _add_pending(self, name: str, batch: Columns) -> None:
        self._pending[name].append(batch)
        self._pending_rows[name] += len(batch[self.specs[name].columns[0].name])
        if self._pending_rows[name] >= self._write_rows[name]:
            self._write_pending(name)

    def _write_pending(self, name: str) -> None:
        if self._pending[name]:
            batches, self._pending[name], self._pending_rows[name] = self._pending[name], [], 0
            self._write(name, batches)

    def _write(self, name: str, batches: list[Columns], *, guarded: bool = True) -> None:
        """Append batches to a stream; ``guarded`` writes stop when the disk runs low."""
        assert self._file is not None
        if guarded:
            self._check_space(batches)
        if guarded and self._fault_reason:
            rows = sum(len(next(iter(b.values()))) for b in batches)
            self._count_drop(name, rows, "disk-full")
            return
        spec = self.specs[name]
        first_row = self.stats[name].rows_written
        columns = {c.name: np.concatenate([b[c.name] for b in batches]) if len(batches) > 1 else batches[0][c.name]
                   for c in spec.columns}
        n = len(columns[spec.columns[0].name])
        for c in spec.columns:
            ds = self._datasets[name][c.name]
            ds.resize((first_row + n, *c.shape))
            ds[first_row:] = columns[c.name]
        self.stats[name].rows_written = first_row + n
        if name == "events":
            self._after_events(batches, columns["t_device_us"], first_row)
        elif name == "ft":
            self._online["ft"].add(self._ft_unwrap(columns["t_device_us"]), columns["t_host_us"])

    def _after_events(self, batches: list[Columns], t_device_us: npt.NDArray[np.int64], first_row: int) -> None:
        assert self._file is not None
        group = self._file["streams/events"]
        had_start = self._event_index.start_bin >= 0
        index_rows = self._event_index.extend(t_device_us, first_row)
        if index_rows.size:
            ds = self._datasets["events"]["index_first_row"]
            n = ds.shape[0]
            ds.resize((n + index_rows.size,))
            ds[n:] = index_rows
            if not had_start:
                group["index_start_bin"][0] = self._event_index.start_bin
        end_rows, t_dev, t_host = [], [], []
        row = first_row
        for b in batches:
            k = len(b["t_device_us"])
            row += k
            if k:
                end_rows.append(row)
                t_dev.append(int(b["t_device_us"][-1]))
                t_host.append(int(b["_t_host_us"][0]))
        if end_rows:
            packets = {
                "end_row": np.array(end_rows, np.int64),
                "t_device_us": np.array(t_dev, np.int64),
                "t_host_us": np.array(t_host, np.int64),
            }
            self._add_pending("event_packets", packets)
            self._online["camera"].add(packets["t_device_us"], packets["t_host_us"])

    def _apply_phases(self) -> None:
        while True:
            try:
                kind, name, t_us = self._phase_queue.get_nowait()
            except queue.Empty:
                break
            if kind == "begin":
                self._phases.begin(name, t_us)
            else:
                self._phases.end(t_us)
        with self._drop_lock:
            drops, self._drops_pending = self._drops_pending, []
        if drops:
            t, stream, counts, reason = zip(*drops)
            self._write_small("drops", {"t_host_us": t, "stream": stream, "rows": counts, "reason": reason})
        if self._phases.dirty:
            assert self._file is not None
            group = stream_group(self._file, "phases")
            rows = self._phases.rows
            for i, key in enumerate(("name", "t_start_us", "t_end_us")):
                ds = group[key]
                ds.resize((len(rows),))
                ds[:] = np.array([r[i] for r in rows], dtype=ds.dtype)
            self.stats["phases"].rows_written = len(rows)
            self._phases.dirty = False

    def _write_small(self, name: str, columns: dict[str, Any]) -> None:
        spec = self.specs[name]
        self._write(name, [{c.name: _as_rows(columns[c.name], c) for c in spec.columns}], guarded=False)

    def _flush_and_commit(self) -> None:
        assert self._file is not None
        self._file.flush()
        commits = self._file[schema.COMMITS_PATH]
        counts = np.array([[self.stats[name].rows_written for name in commits.attrs["streams"]]], dtype=np.int64)
        t = np.array([self.host_us()], dtype=np.int64)
        n = commits["rows"].shape[0]
        commits["rows"].resize((n + 1, counts.shape[1]))
        commits["rows"][n:] = counts
        commits["t_host_us"].resize((n + 1,))
        commits["t_host_us"][n:] = t
        self._file.flush()
        if self.on_commit is not None:
            self.on_commit({str(k): v for k, v in zip(commits.attrs["streams"], counts[0].tolist())})

    def _check_space(self, batches: list[Columns]) -> None:
        if self._fault_reason or self.min_free_bytes is None:
            return
        needed = sum(a.nbytes for b in batches for a in b.values())
        headroom = _write_headroom(self.partial)
        if headroom < self.min_free_bytes + 2 * needed:
            self._fault_reason = f"disk full: only {headroom / 1e6:.1f} MB left for {self.partial.name}"

    def _root_attrs(self) -> dict[str, Any]:
        md = self.metadata
        attrs: dict[str, Any] = {
            "schema": schema.SCHEMA_NAME,
            "schema_version": schema.SCHEMA_VERSION,
            "labrig_version": __version__,
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "host_clock": "monotonic, integer nanoseconds",
            "time_base": "t_host_us: host microseconds since t0_host_ns",
            "t0_host_ns": np.int64(self.t0_host_ns),
            "indenter": md.indenter,
            "indenter_definition": md.indenter_toml,
            "protocol": md.protocol_toml,
            "rig": md.rig_toml,
            "gel": md.gel_toml,
            "bulk_codec": self.bulk_codec,
            "portable_codec": PORTABLE_CODEC,
            "exit_status": schema.EXIT_RECORDING,
            "exit_reason": "",
            "finalized": False,
        }
        for key, value in md.extra.items():
            attrs[f"extra_{key}"] = value
        return attrs


def _as_rows(values: npt.ArrayLike, column: schema.Column) -> npt.NDArray[Any]:
    arr = np.array(values, dtype=column.np_dtype, copy=True)
    if arr.ndim == len(column.shape):
        arr = arr.reshape((1, *column.shape))
    if arr.shape[1:] != column.shape:
        raise ValueError(f"column {column.name!r}: rows of shape {arr.shape[1:]}, expected {column.shape}")
    return arr


def _write_headroom(path: Path) -> int:
    """Bytes this process may still add to ``path``: free disk space or file-size limit."""
    st = os.statvfs(path.parent)
    free = st.f_bavail * st.f_frsize
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    if soft != resource.RLIM_INFINITY:
        free = min(free, soft - path.stat().st_size)
    return free


def _describe_write_failure(exc: BaseException) -> str:
    text = str(exc)
    code = getattr(exc, "errno", None)
    if code in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT) or any(
        f"errno = {c}," in text for c in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT)
    ):
        return "disk full (the write failed)"
    return f"write failed ({type(exc).__name__}: {text.splitlines()[0] if text else ''})"


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
