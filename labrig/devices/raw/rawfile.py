"""Whole RAW files: read one into arrays (:func:`read_raw`), stream one (:func:`iter_raw`), write one (:func:`write_raw`)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.devices.raw.evt2 import Evt2Decoder, encode_evt2
from labrig.devices.raw.evt3 import Evt3Decoder, encode_evt3
from labrig.devices.raw.header import RawHeader, make_header, read_header
from labrig.devices.raw.stream import Decoded, StreamDecoder

#: Payloads up to this size are read in one piece; larger ones are streamed in CHUNK_BYTES pieces.
WHOLE_READ_MAX = 256 << 20
CHUNK_BYTES = 64 << 20

_DECODERS: dict[str, type[StreamDecoder]] = {"EVT3": Evt3Decoder, "EVT2": Evt2Decoder}


class RawFormatError(ValueError):
    """The file's event format is unknown (no usable header) or not supported."""


@dataclass(frozen=True)
class RawFile:
    """A decoded RAW file.

    ``events`` (x, y, p, t; t absolute sensor time in us, unwrapped, as Prophesee's standalone
    decoders report it), ``triggers`` (p, t, id), the parsed ``header``, ``geometry``
    (width, height; None if neither header nor sensor tells), ``format`` ('EVT3' / 'EVT2').
    ``skipped_words`` counts words not decoded (see SkipReason); ``skips`` lists their runs
    (file byte offset, words, reason), the first MAX_SKIP_RUNS of ``skip_runs_total``.
    """

    path: Path
    format: str
    header: RawHeader
    geometry: tuple[int, int] | None
    events: npt.NDArray[Any]
    triggers: npt.NDArray[Any]
    skipped_words: int
    skips: npt.NDArray[Any]
    skip_runs_total: int
    dropped_events: int
    others_words: int
    time_high_loops: int

    @property
    def payload_offset(self) -> int:
        """Byte offset of the first payload byte (the header's size)."""
        return self.header.size


def open_decoder(
    path: str | os.PathLike[str], format: str | None = None, geometry: tuple[int, int] | None = None
) -> tuple[RawHeader, str, tuple[int, int] | None, StreamDecoder]:
    """Header, format, geometry and a fresh decoder for ``path`` (format/geometry override the header's)."""
    header = read_header(os.fspath(path))
    fmt = (format or header.format_name() or "").upper()
    if not fmt:
        raise RawFormatError(f"{path}: no format in the header (no format/evt/system_ID key); pass format='EVT3' or 'EVT2'")
    if fmt not in _DECODERS:
        raise RawFormatError(f"{path}: format {fmt} is not supported (only {sorted(_DECODERS)})")
    geo = geometry or header.geometry()
    width, height = geo if geo else (None, None)
    return header, fmt, geo, _DECODERS[fmt](width, height, offset=header.size)


def iter_raw(
    path: str | os.PathLike[str],
    chunk_bytes: int = CHUNK_BYTES,
    format: str | None = None,
    geometry: tuple[int, int] | None = None,
) -> Iterator[Decoded]:
    """Decode ``path`` chunk by chunk: yields (events, triggers) per chunk of ``chunk_bytes`` payload bytes."""
    header, _, _, decoder = open_decoder(path, format, geometry)
    with open(path, "rb") as f:
        f.seek(header.size)
        while chunk := f.read(chunk_bytes):
            yield decoder.feed(chunk)
    decoder.finish()


def read_raw(path: str | os.PathLike[str], format: str | None = None, geometry: tuple[int, int] | None = None) -> RawFile:
    """Decode the whole RAW file at ``path`` (EVT 3.0 or EVT 2.0, from its header unless ``format`` is given).

    Corrupt or truncated payloads decode what is valid; what was not is in ``skipped_words`` / ``skips``.
    Raises RawFormatError when the format cannot be told, OSError when the file cannot be read.
    """
    header, fmt, geo, decoder = open_decoder(path, format, geometry)
    size = os.stat(path).st_size - header.size
    if size <= WHOLE_READ_MAX:
        payload = np.fromfile(path, dtype=np.uint8, offset=header.size)
        out = decoder.feed(payload)
        events, triggers = out.events, out.triggers
    else:
        parts: list[Decoded] = []
        with open(path, "rb") as f:
            f.seek(header.size)
            while chunk := f.read(CHUNK_BYTES):
                parts.append(decoder.feed(chunk))
        events = np.concatenate([p.events for p in parts])
        triggers = np.concatenate([p.triggers for p in parts])
    decoder.finish()
    return RawFile(
        path=Path(path),
        format=fmt,
        header=header,
        geometry=geo,
        events=events,
        triggers=triggers,
        skipped_words=decoder.skipped_words,
        skips=decoder.skips,
        skip_runs_total=decoder.skip_runs_total,
        dropped_events=decoder.dropped_events,
        others_words=decoder.others_words,
        time_high_loops=decoder.time_high_loops,
    )


def write_raw(
    path: str | os.PathLike[str],
    events: npt.NDArray[Any],
    triggers: npt.NDArray[Any] | None = None,
    *,
    format: str = "EVT3",
    width: int = 1280,
    height: int = 720,
    header: dict[str, str] | None = None,
) -> int:
    """Write an EVK4-like RAW file (sorted header with ``% end``, then the payload); returns its size in bytes.

    ``header`` adds or replaces header keys (e.g. serial_number, date).
    """
    fmt = format.upper()
    if fmt == "EVT3":
        payload = encode_evt3(events, triggers, width=width, height=height)
    elif fmt == "EVT2":
        payload = encode_evt2(events, triggers, width=width, height=height)
    else:
        raise RawFormatError(f"cannot write format {format!r} (only EVT3, EVT2)")
    head = make_header(fmt, width, height, header)
    tmp = Path(os.fspath(path) + ".partial")
    with open(tmp, "wb") as f:
        f.write(head)
        f.write(payload)
    os.replace(tmp, path)
    return len(head) + len(payload)
