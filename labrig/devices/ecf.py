"""Metavision HDF5 event files (``.hdf5``) without the HDF5 ECF plugin.

Prophesee's HDF5 files keep CD events in ``/CD/events`` (compound x u2, y u2, p i2, t i8;
chunks of 16384 events) compressed with their ECF codec (HDF5 filter 0x8ECF), which h5py cannot
run. We read the stored chunks as bytes (``dsid.read_direct_chunk``) and decode ECF here, so
plain h5py is enough. ``/EXT_TRIGGER/events`` chunks are stored uncompressed and read normally.

ECF chunk layout (events.md section 4), all little-endian:

* u32 header: ``count << 2 | ys_xs_ps_packed << 1 | xs_ps_packed``;
* u64 first timestamp, then timestamp run bytes: high nibble = step from the current time
  (0..14), low nibble = how many events have that time (15: the count is the next u16); a byte
  whose high nibble is 15 is an escape: the low nibbles of consecutive escape bytes, least
  significant first, add a large step;
* ``ys_xs_ps_packed``: four events per three u32, 24 bits each ``y << 12 | x << 1 | p``;
* otherwise runs of y as u16 ``y << 5 | count`` (count 31: the count is the next u16), then
  either four events per three u16, 12 bits each ``x << 1 | p`` (``xs_ps_packed``), or
  *masked x*: u16 ``x << 5 | mask`` where mask bit (4 - j) adds an event at x + j + 1, then runs
  of p as bytes ``p << 7 | count`` (count 127: the count is the next u16).

The byte loops are numba-compiled (cached on disk) like the RAW decoders; numba is imported
with this module, h5py when a file is opened.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from labrig.devices.raw.header import RawHeader
from labrig.devices.raw.stream import TRIGGER_DTYPE
from labrig.errors import LabrigError
from labrig.eventtypes import EVENT_DTYPE

#: HDF5 filter id of Prophesee's ECF codec.
ECF_FILTER_ID = 0x8ECF
#: Most events one ECF chunk can hold (the count is checked against it).
MAX_CHUNK_EVENTS = 65535
#: Events per chunk in files the Metavision SDK writes.
METAVISION_CHUNK_EVENTS = 16384
#: Index bucket width of ``/CD/indexes`` and ``/EXT_TRIGGER/indexes``, us.
INDEX_BUCKET_US = 2000

#: ``/CD/events`` rows as stored (16 bytes: x, y, p, padding, t).
METAVISION_CD_DTYPE = np.dtype(
    {"names": ["x", "y", "p", "t"], "formats": ["<u2", "<u2", "<i2", "<i8"], "offsets": [0, 2, 4, 8], "itemsize": 16}
)
#: ``/EXT_TRIGGER/events`` rows as stored (24 bytes).
METAVISION_TRIGGER_DTYPE = np.dtype(
    {"names": ["p", "t", "id"], "formats": ["<i2", "<i8", "<i2"], "offsets": [0, 8, 16], "itemsize": 24}
)
METAVISION_INDEX_DTYPE = np.dtype([("id", "<u8"), ("ts", "<i8")])

#: Encoding modes of :func:`encode_ecf_chunk`.
MODES = ("auto", "ys_xs_ps_packed", "xs_ps_packed", "masked")


class EcfError(LabrigError):
    """An ECF chunk or a Metavision HDF5 file cannot be decoded."""


# -- chunk codec ------------------------------------------------------------------------------


def decode_ecf_chunk(data: bytes | bytearray | memoryview | npt.NDArray[np.uint8]) -> npt.NDArray[Any]:
    """Events (EVENT_DTYPE) of one ECF-compressed chunk; EcfError if it is truncated or corrupt."""
    buf = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else np.ascontiguousarray(data, np.uint8)
    if buf.size < 12:
        raise EcfError(f"ECF chunk of {buf.size} bytes is shorter than its 12-byte header")
    n = int(buf[:4].view("<u4")[0]) >> 2
    if n > MAX_CHUNK_EVENTS:
        raise EcfError(f"ECF chunk says {n} events, more than the codec's {MAX_CHUNK_EVENTS}")
    out = np.empty(n, EVENT_DTYPE)
    # a masked-x word may name up to 5 events past the count (ignored, as Prophesee's decoder does)
    spill = np.empty(5, np.uint16)
    status = _decode_kernel(buf, n, out["x"], out["y"], out["p"], out["t"], spill)
    if status < 0:
        what = {-1: "truncated", -2: "corrupt (a run goes past the event count)"}.get(status, "corrupt")
        raise EcfError(f"ECF chunk of {buf.size} bytes ({n} events) is {what}")
    return out


def encode_ecf_chunk(events: npt.NDArray[Any], mode: str = "auto") -> bytes:
    """One ECF chunk for ``events`` (fields x, y, p, t; at most MAX_CHUNK_EVENTS).

    ``mode``: "ys_xs_ps_packed", "xs_ps_packed", "masked" or "auto" (packed (y, x, p) when rows
    rarely repeat from one event to the next, masked x when events often come in short runs
    along a row, else packed (x, p)). Like the codec itself, times that go back within a chunk
    are written as a step of 0 (ECF is lossless only for non-decreasing times).
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, not {mode!r}")
    n = int(events.shape[0])
    if n > MAX_CHUNK_EVENTS:
        raise ValueError(f"an ECF chunk holds at most {MAX_CHUNK_EVENTS} events, got {n}")
    pad = 8
    x = np.zeros(n + pad, np.int64)
    y = np.zeros(n + pad, np.int64)
    p = np.zeros(n + pad, np.int64)
    t = np.asarray(events["t"], np.int64)
    x[:n], y[:n], p[:n] = events["x"], events["y"], events["p"]
    if n and (x[:n].max() >= 2048 or y[:n].max() >= 2048 or x[:n].min() < 0 or y[:n].min() < 0):
        raise ValueError("ECF holds 11-bit coordinates (0..2047)")
    if n and not np.isin(p[:n], (0, 1)).all():
        raise ValueError("event p must be 0 or 1")
    if mode == "auto":
        mode = _choose_mode(x[:n], y[:n])
    code = {"ys_xs_ps_packed": 2, "xs_ps_packed": 1, "masked": 0}[mode]
    out = np.empty(64 + 32 * n, np.uint8)  # worst case: 17 B of time per event, 4 B of y, 2 B of x, 3 B of p
    k = _encode_kernel(x, y, p, t, n, code, out)
    return out[:k].tobytes()


def _choose_mode(x: npt.NDArray[np.int64], y: npt.NDArray[np.int64]) -> str:
    if x.size < 2:
        return "ys_xs_ps_packed"
    same_row = float(np.mean(y[1:] == y[:-1]))
    if same_row < 0.2:
        return "ys_xs_ps_packed"
    step = x[1:] - x[:-1]
    neighbours = float(np.mean((step > 0) & (step <= 5) & (y[1:] == y[:-1])))
    return "masked" if neighbours > 0.3 else "xs_ps_packed"


# -- files ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class MetavisionFile:
    """What a Metavision HDF5 file holds: ``events`` (EVENT_DTYPE, t in us as stored, i.e.
    absolute sensor time unless the writer shifted it), ``triggers`` (TRIGGER_DTYPE), the root
    attributes and the geometry (None when the file does not say)."""

    path: Path
    events: npt.NDArray[Any]
    triggers: npt.NDArray[Any]
    attrs: dict[str, str] = field(default_factory=dict)
    geometry: tuple[int, int] | None = None
    chunks: int = 0


def _open_h5(path: str | os.PathLike[str]) -> Any:
    import h5py

    p = Path(path)
    if not p.is_file():
        raise EcfError(f"{p}: no such file")
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise EcfError(f"{p} is not an HDF5 file ({str(exc).splitlines()[0]})") from None
    if "CD" not in f or "events" not in f["CD"]:
        f.close()
        raise EcfError(f"{p} is not a Metavision HDF5 event file (no /CD/events)")
    return f


def _attrs(f: Any) -> dict[str, str]:
    out = {}
    for key, value in f.attrs.items():
        out[key] = value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)
    return out


def geometry_from_attrs(attrs: dict[str, str]) -> tuple[int, int] | None:
    """(width, height) from the ``geometry`` (WxH) or ``format`` (NAME;width=..;height=..) attribute."""
    return RawHeader(fields=dict(attrs)).geometry()


def metavision_event_count(path: str | os.PathLike[str]) -> int:
    """Rows in ``/CD/events`` (without decoding)."""
    with _open_h5(path) as f:
        return int(f["CD/events"].shape[0])


def iter_metavision_chunks(path: str | os.PathLike[str]) -> Iterator[npt.NDArray[Any]]:
    """Decode ``/CD/events`` chunk by chunk (EVENT_DTYPE arrays, file order)."""
    with _open_h5(path) as f:
        yield from _iter_cd(f, Path(path))


def _iter_cd(f: Any, path: Path) -> Iterator[npt.NDArray[Any]]:
    ds = f["CD/events"]
    n_rows = int(ds.shape[0])
    if n_rows == 0:
        return
    if ds.chunks is None or len(ds.chunks) != 1:
        raise EcfError(f"{path}: /CD/events is not chunked; not a Metavision event file")
    names = ds.dtype.names or ()
    if not {"x", "y", "p", "t"} <= set(names):
        raise EcfError(f"{path}: /CD/events has fields {names}, expected x, y, p, t")
    dcpl = ds.id.get_create_plist()
    filters = [dcpl.get_filter(i)[0] for i in range(dcpl.get_nfilters())]
    chunk = int(ds.chunks[0])
    dsid = ds.id
    for start in range(0, n_rows, chunk):
        rows = min(chunk, n_rows - start)
        try:
            mask, data = dsid.read_direct_chunk((start,))
        except (OSError, RuntimeError, ValueError) as exc:  # a chunk never written
            raise EcfError(f"{path}: /CD/events chunk at row {start} cannot be read ({str(exc).splitlines()[0]})") from None
        if ECF_FILTER_ID in filters and not mask & (1 << filters.index(ECF_FILTER_ID)):
            events = decode_ecf_chunk(data)
        elif not filters or all(mask & (1 << i) for i in range(len(filters))):  # stored as plain rows
            rows_raw = np.frombuffer(data, ds.dtype)
            events = np.empty(rows_raw.size, EVENT_DTYPE)
            for name in ("x", "y", "p", "t"):
                events[name] = rows_raw[name]
        else:
            others = [hex(fid) for fid in filters if fid != ECF_FILTER_ID]
            raise EcfError(f"{path}: /CD/events uses HDF5 filters {others} besides ECF; not supported")
        if events.size < rows:
            raise EcfError(f"{path}: /CD/events chunk at row {start} holds {events.size} events, the dataset says {rows}")
        yield events[:rows]


def read_metavision_hdf5(path: str | os.PathLike[str]) -> MetavisionFile:
    """Read a Metavision HDF5 event file (CD events and trigger edges) with plain h5py."""
    p = Path(path)
    with _open_h5(p) as f:
        parts = list(_iter_cd(f, p))
        events = np.concatenate(parts) if parts else np.zeros(0, EVENT_DTYPE)
        triggers = _triggers(f)
        attrs = _attrs(f)
    return MetavisionFile(p, events, triggers, attrs, geometry_from_attrs(attrs), len(parts))


def metavision_attrs(path: str | os.PathLike[str]) -> dict[str, str]:
    """The file's root attributes as text (``serial_number``, ``geometry``, ``date``, ...)."""
    with _open_h5(path) as f:
        return _attrs(f)


def metavision_triggers(path: str | os.PathLike[str]) -> npt.NDArray[Any]:
    """``/EXT_TRIGGER/events`` (stored uncompressed) as TRIGGER_DTYPE; empty when the file has none."""
    with _open_h5(path) as f:
        return _triggers(f)


def _triggers(f: Any) -> npt.NDArray[Any]:
    if "EXT_TRIGGER" not in f or "events" not in f["EXT_TRIGGER"]:
        return np.zeros(0, TRIGGER_DTYPE)
    raw = f["EXT_TRIGGER/events"][:]
    triggers = np.empty(raw.size, TRIGGER_DTYPE)
    triggers["p"], triggers["t"], triggers["id"] = raw["p"], raw["t"], raw["id"]
    return triggers


def write_metavision_hdf5(
    path: str | os.PathLike[str],
    events: npt.NDArray[Any],
    triggers: npt.NDArray[Any] | None = None,
    *,
    attrs: dict[str, str] | None = None,
    chunk_events: int = METAVISION_CHUNK_EVENTS,
    mode: str = "auto",
) -> None:
    """Write events in the Metavision HDF5 layout (ECF-compressed CD chunks written as raw chunks).

    Made for tests and interchange of small files: the layout and indexes follow events.md
    section 4, but it is not checked against the Metavision SDK here.
    """
    import h5py

    triggers = np.zeros(0, TRIGGER_DTYPE) if triggers is None else triggers
    with h5py.File(path, "w") as f:
        for key, value in {"version": "1.0", **(attrs or {})}.items():
            f.attrs[key] = str(value)
        cd = f.create_group("CD")
        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        dcpl.set_chunk((chunk_events,))
        dcpl.set_filter(ECF_FILTER_ID, h5py.h5z.FLAG_OPTIONAL, ())
        space = h5py.h5s.create_simple((events.size,), (h5py.h5s.UNLIMITED,))
        tid = h5py.h5t.py_create(METAVISION_CD_DTYPE, logical=True)
        dsid = h5py.h5d.create(cd.id, b"events", tid, space, dcpl=dcpl)
        for start in range(0, events.size, chunk_events):
            dsid.write_direct_chunk((start,), encode_ecf_chunk(events[start : start + chunk_events], mode), 0)
        cd.create_dataset("indexes", data=_indexes(events["t"]), maxshape=(None,), chunks=(chunk_events,))
        cd["indexes"].attrs["offset"] = str(-int(events["t"][0]) if events.size else 0)
        tr = f.create_group("EXT_TRIGGER")
        rows = np.zeros(triggers.size, METAVISION_TRIGGER_DTYPE)
        rows["p"], rows["t"], rows["id"] = triggers["p"], triggers["t"], triggers["id"]
        tr.create_dataset("events", data=rows, maxshape=(None,), chunks=(chunk_events,))
        tr.create_dataset("indexes", data=_indexes(triggers["t"]), maxshape=(None,), chunks=(chunk_events,))
        tr["indexes"].attrs["offset"] = str(-int(triggers["t"][0]) if triggers.size else 0)


def _indexes(t: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """Entry 0 = (0, -1); entry j >= 1 = first row of bucket j-1 and its time from the first event (empty: previous)."""
    if t.size == 0:
        return np.zeros(0, METAVISION_INDEX_DTYPE)
    rel = np.asarray(t, np.int64) - int(t[0])
    bucket = np.maximum(rel, 0) // INDEX_BUCKET_US
    n_buckets = int(bucket.max()) + 1
    first = np.searchsorted(np.maximum.accumulate(bucket), np.arange(n_buckets), side="left")
    out = np.zeros(n_buckets + 1, METAVISION_INDEX_DTYPE)
    out[0] = (0, -1)
    prev_id, prev_ts = 0, -1
    for j in range(n_buckets):
        i = int(first[j])
        if i < rel.size and bucket[i] == j:
            prev_id, prev_ts = i, int(rel[i])
        out[j + 1] = (prev_id, prev_ts)
    return out


# -- byte loops (numba) ---------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _u16(buf, pos):  # type: ignore[no-untyped-def]
    return np.int64(buf[pos]) | (np.int64(buf[pos + 1]) << 8)


@njit(cache=True, nogil=True)
def _u32(buf, pos):  # type: ignore[no-untyped-def]
    return _u16(buf, pos) | (_u16(buf, pos + 2) << 16)


@njit(cache=True, nogil=True)
def _decode_kernel(buf, n, x, y, p, t, sx):  # type: ignore[no-untyped-def]
    """Decode one chunk into x, y, p, t (n long; sx takes masked-x spill); bytes used, -1 truncated, -2 corrupt."""
    nb = buf.shape[0]
    info = _u32(buf, 0)
    cur = np.int64(0)
    for b in range(8):
        cur |= np.int64(buf[4 + b]) << (8 * b)
    pos = 12
    i = 0
    while i < n:  # timestamps
        if pos >= nb:
            return -1
        v = np.int64(buf[pos])
        hi = v >> 4
        c = v & 15
        if hi != 15:
            cur += hi
            if c == 15:
                if pos + 2 >= nb:
                    return -1
                c = _u16(buf, pos + 1)
                pos += 2
            pos += 1
            if i + c > n:
                return -2
            for k in range(c):
                t[i + k] = cur
            i += c
        else:  # escape bytes: a large step, 4 bits per byte, least significant first
            shift = 0
            while hi == 15:
                if shift > 60:
                    return -2
                cur += c << shift
                shift += 4
                pos += 1
                if pos >= nb:
                    return -1
                v = np.int64(buf[pos])
                hi = v >> 4
                c = v & 15
    if (info >> 1) & 1:  # (y, x, p) packed, 4 events in 3 u32
        for g in range(0, n, 4):
            if pos + 12 > nb:
                return -1
            w0 = _u32(buf, pos)
            w1 = _u32(buf, pos + 4)
            w2 = _u32(buf, pos + 8)
            pos += 12
            for j in range(min(4, n - g)):
                if j == 0:
                    v = w0 >> 8
                elif j == 1:
                    v = (w0 & 0xFF) | ((w1 >> 16) << 8)
                elif j == 2:
                    v = (w1 & 0xFFFF) | ((w2 >> 24) << 16)
                else:
                    v = w2 & 0xFFFFFF
                y[g + j] = (v >> 12) & 0x7FF
                x[g + j] = (v >> 1) & 0x7FF
                p[g + j] = v & 1
        return pos
    i = 0
    while i < n:  # runs of y
        if pos + 2 > nb:
            return -1
        v = _u16(buf, pos)
        pos += 2
        c = v & 31
        if c == 31:
            if pos + 2 > nb:
                return -1
            c = _u16(buf, pos)
            pos += 2
        if i + c > n:
            return -2
        for k in range(c):
            y[i + k] = v >> 5
        i += c
    if info & 1:  # (x, p) packed, 4 events in 3 u16
        for g in range(0, n, 4):
            if pos + 6 > nb:
                return -1
            w0 = _u16(buf, pos)
            w1 = _u16(buf, pos + 2)
            w2 = _u16(buf, pos + 4)
            pos += 6
            for j in range(min(4, n - g)):
                if j == 0:
                    v = w0 >> 4
                elif j == 1:
                    v = (w0 & 0xF) | ((w1 >> 8) << 4)
                elif j == 2:
                    v = (w1 & 0xFF) | ((w2 >> 12) << 8)
                else:
                    v = w2 & 0xFFF
                x[g + j] = v >> 1
                p[g + j] = v & 1
        return pos
    i = 0
    while i < n:  # masked x: x and up to 5 neighbours to its right
        if pos + 2 > nb:
            return -1
        v = _u16(buf, pos)
        pos += 2
        x0 = v >> 5
        x[i] = x0
        i += 1
        for j in range(5):
            if v & (1 << (4 - j)):
                if i < n:
                    x[i] = x0 + j + 1
                else:
                    sx[i - n] = x0 + j + 1
                i += 1
    i = 0
    while i < n:  # runs of p
        if pos >= nb:
            return -1
        v = np.int64(buf[pos])
        pos += 1
        c = v & 127
        if c == 127:
            if pos + 2 > nb:
                return -1
            c = _u16(buf, pos)
            pos += 2
        if i + c > n:
            return -2
        for k in range(c):
            p[i + k] = v >> 7
        i += c
    return pos


@njit(cache=True, nogil=True)
def _put16(out, k, v):  # type: ignore[no-untyped-def]
    out[k] = v & 0xFF
    out[k + 1] = (v >> 8) & 0xFF
    return k + 2


@njit(cache=True, nogil=True)
def _put32(out, k, v):  # type: ignore[no-untyped-def]
    _put16(out, k, v & 0xFFFF)
    return _put16(out, k + 2, (v >> 16) & 0xFFFF)


@njit(cache=True, nogil=True)
def _encode_kernel(x, y, p, t, n, code, out):  # type: ignore[no-untyped-def]
    """Encode n events (x, y, p padded by >= 4 zeros) into ``out``; code 2 (y,x,p) packed, 1 (x,p) packed, 0 masked x."""
    k = _put32(out, 0, (n << 2) | (2 if code == 2 else 0) | (1 if code == 1 else 0))
    cur = t[0] if n else np.int64(0)
    for b in range(8):
        out[k + b] = (cur >> (8 * b)) & 0xFF
    k += 8
    i = 0
    while i < n:
        ti = t[i]
        if ti >= cur + 15:
            dt = ti - cur
            while dt > 0:
                out[k] = 0xF0 | (dt & 15)
                k += 1
                dt >>= 4
            cur = ti
        step = 0
        if ti >= cur:
            step = ti - cur
            cur = ti
        c = 1
        while i + c < n and t[i + c] == cur:
            c += 1
        if c >= 15:
            out[k] = (step << 4) | 15
            k = _put16(out, k + 1, c)
        else:
            out[k] = (step << 4) | c
            k += 1
        i += c
    if code == 2:
        for g in range(0, n, 4):
            v0 = (y[g] << 12) | (x[g] << 1) | p[g]
            v1 = (y[g + 1] << 12) | (x[g + 1] << 1) | p[g + 1]
            v2 = (y[g + 2] << 12) | (x[g + 2] << 1) | p[g + 2]
            v3 = (y[g + 3] << 12) | (x[g + 3] << 1) | p[g + 3]
            k = _put32(out, k, (v0 << 8) | (v1 & 0xFF))
            k = _put32(out, k, ((v1 >> 8) << 16) | (v2 & 0xFFFF))
            k = _put32(out, k, ((v2 >> 16) << 24) | (v3 & 0xFFFFFF))
        return k
    i = 0
    while i < n:
        c = 1
        while i + c < n and y[i + c] == y[i]:
            c += 1
        if c >= 31:
            k = _put16(out, k, (y[i] << 5) | 31)
            k = _put16(out, k, c)
        else:
            k = _put16(out, k, (y[i] << 5) | c)
        i += c
    if code == 1:
        for g in range(0, n, 4):
            v0 = (x[g] << 1) | p[g]
            v1 = (x[g + 1] << 1) | p[g + 1]
            v2 = (x[g + 2] << 1) | p[g + 2]
            v3 = (x[g + 3] << 1) | p[g + 3]
            k = _put16(out, k, (v0 << 4) | (v1 & 0xF))
            k = _put16(out, k, ((v1 >> 4) << 8) | (v2 & 0xFF))
            k = _put16(out, k, ((v2 >> 8) << 12) | (v3 & 0xFFF))
        return k
    i = 0
    while i < n:
        x0 = x[i]
        i += 1
        m = 0
        for j in range(5):
            if i < n and x[i] == x0 + j + 1:
                m |= 1 << (4 - j)
                i += 1
        k = _put16(out, k, (x0 << 5) | m)
    i = 0
    while i < n:
        c = 1
        while i + c < n and p[i + c] == p[i]:
            c += 1
        if c >= 127:
            out[k] = (p[i] << 7) | 127
            k = _put16(out, k + 1, c)
        else:
            out[k] = (p[i] << 7) | c
            k += 1
        i += c
    return k
