"""Prophesee RAW event files: EVT 3.0 / EVT 2.0 streaming decoders and encoders, header parsing.

>>> raw = read_raw("recording.raw")          # doctest: +SKIP
>>> raw.events["t"], raw.triggers, raw.geometry, raw.skipped_words  # doctest: +SKIP

Decoding semantics follow Prophesee's standalone decoders (absolute sensor time, unwrapped,
int64 us; words before the first TIME_HIGH skipped); the word loops are numba-compiled and
cached on disk, numba being imported on the first decode or encode only.
"""

from labrig.devices.raw.evt2 import Evt2Decoder, encode_evt2
from labrig.devices.raw.evt3 import Evt3Decoder, encode_evt3
from labrig.devices.raw.evt3_stream import Evt3StreamEncoder
from labrig.devices.raw.header import RawHeader, make_header, parse_header, read_header
from labrig.devices.raw.rawfile import RawFile, RawFormatError, iter_raw, open_decoder, read_raw, write_raw
from labrig.devices.raw.stream import (
    EVENT_DTYPE,
    MAX_SKIP_RUNS,
    SKIP_DTYPE,
    TRIGGER_DTYPE,
    Decoded,
    SkipReason,
    StreamDecoder,
)

__all__ = [
    "EVENT_DTYPE",
    "MAX_SKIP_RUNS",
    "SKIP_DTYPE",
    "TRIGGER_DTYPE",
    "Decoded",
    "Evt2Decoder",
    "Evt3Decoder",
    "Evt3StreamEncoder",
    "RawFile",
    "RawFormatError",
    "RawHeader",
    "SkipReason",
    "StreamDecoder",
    "encode_evt2",
    "encode_evt3",
    "iter_raw",
    "make_header",
    "open_decoder",
    "parse_header",
    "read_header",
    "read_raw",
    "write_raw",
]
