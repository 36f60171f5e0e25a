"""Recovering a recording that was never finalized (crash, kill -9, disk full).

The crashed ``NAME.partial`` is still marked as open by its SWMR writer, so it
is read in SWMR mode and copied, stream by stream and truncated to the last
commit, into ``NAME.recovering``; that copy is finalized (clock models,
exit status ``crashed-recovered``), checked, and renamed to ``NAME``. The
partial file is removed only after the recovered file has been verified.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import h5py

from labrig.errors import RecordingError
from labrig.recording import schema
from labrig.recording.finalize import committed_rows, finalize_file
from labrig.recording.layout import PARTIAL_SUFFIX, final_path, stream_path
from labrig.recording.quality import store_quality
from labrig.recording.reader import Recording, TruncatedRecording, open_h5


@dataclass(frozen=True)
class RecoveryResult:
    path: Path
    rows: dict[str, int]
    lost_rows: dict[str, int]


def resolve_partial(path: Path) -> Path:
    """Accept ``NAME.partial`` or ``NAME`` whose partial file exists."""
    if path.name.endswith(PARTIAL_SUFFIX):
        return path
    candidate = path.with_name(path.name + PARTIAL_SUFFIX)
    if candidate.exists():
        return candidate
    if path.exists():
        return path
    raise RecordingError(f"{path}: no such file, and no {candidate.name} beside it")


def recover(path: str | os.PathLike[str], *, keep_partial: bool = False) -> RecoveryResult:
    """Finalize a crashed recording; returns where the recovered file is."""
    source = resolve_partial(Path(path))
    with _open_source(source) as src:
        if src.attrs.get("schema") != schema.SCHEMA_NAME:
            raise RecordingError(f"{source} is not a labrig recording")
        if bool(src.attrs.get("finalized", False)):
            raise RecordingError(f"{source} is already finalized; nothing to recover")
        target = final_path(source)
        if target == source:
            target = source.with_name(source.stem + ".recovered" + source.suffix)
        if target.exists():
            raise RecordingError(f"{target} already exists; move it away before recovering {source.name}")
        work = target.with_name(target.name + ".recovering")
        rows = committed_rows(src) or dict.fromkeys(src[schema.COMMITS_PATH].attrs["streams"], 0)
        lost = _copy_truncated(src, work, rows)
    finalize_file(work, schema.EXIT_RECOVERED, "finalized by labrig recover after the recorder stopped unexpectedly")
    with Recording(work) as check:
        got = {name: check.rows(name) for name in rows}
    if got != rows:
        raise RecordingError(f"recovered copy of {source} holds {got}, expected {rows}; the partial file was kept")
    store_quality(work)
    os.replace(work, target)
    if not keep_partial:
        source.unlink()
    return RecoveryResult(target, rows, lost)


def _open_source(source: Path) -> h5py.File:
    """Open the crashed file; if a failed flush left it shorter than its
    superblock says, extend it (sparse zeros past the end, no existing byte
    changes) so HDF5 opens it. Only committed rows are trusted anyway."""
    try:
        return open_h5(source)
    except TruncatedRecording as short:
        if not source.name.endswith(PARTIAL_SUFFIX) or short.stored_eof <= short.eof:
            raise
        os.truncate(source, short.stored_eof)
        return open_h5(source)


def _copy_truncated(src: h5py.File, work: Path, rows: dict[str, int]) -> dict[str, int]:
    """Copy everything to ``work``, cutting each stream at its committed rows."""
    lost: dict[str, int] = {}
    with h5py.File(work, "w", libver="latest") as dst:
        for key, value in src.attrs.items():
            dst.attrs[key] = value
        for name in src:
            src.copy(src[name], dst, name=name)
        for stream, n in rows.items():
            group = dst[stream_path(stream)]
            for key, ds in group.items():
                if isinstance(ds, h5py.Dataset) and not key.startswith("index_") and ds.shape[0] > n:
                    lost[stream] = max(lost.get(stream, 0), ds.shape[0] - n)
                    ds.resize((n, *ds.shape[1:]))
        events = dst[stream_path("events")]
        index = events["index_first_row"]
        keep = int((index[:] <= rows.get("events", 0)).sum())
        index.resize((keep,))
    return lost
