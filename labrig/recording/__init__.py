"""Recordings: one HDF5 file per probing run (format v1, docs/recording-format.md)."""

from labrig.recording.reader import EVENT_DTYPE, Phase, Recording
from labrig.recording.recover import RecoveryResult, recover
from labrig.recording.writer import RecordingMetadata, RecordingResult, RecordingWriter

__all__ = [
    "EVENT_DTYPE",
    "Phase",
    "Recording",
    "RecordingMetadata",
    "RecordingResult",
    "RecordingWriter",
    "RecoveryResult",
    "recover",
]
