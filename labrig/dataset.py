"""A campaign output folder: its manifest, the recordings it lists by split, their ground-truth sidecars.

Layout (``labrig campaign FILE --out FOLDER``)::

    FOLDER/manifest.csv   one row per planned recording, columns MANIFEST_COLUMNS
    FOLDER/ID.h5          a recording (a crash leaves ID.h5.partial, set aside as ID.h5.partial.N)
    FOLDER/ID.gt.h5       its ground truth (``labrig groundtruth FOLDER``), never inside the recording
    FOLDER/ID.events.toml the contrast thresholds of the camera that made it, where they are its own (a
                          virtual-time campaign that varies them: ``labrig calibrate events`` on that camera)

The campaign writes the manifest (:func:`write_manifest`, atomically after each recording);
``labrig groundtruth``, ``labrig train`` and ``labrig evaluate`` read it through
:class:`Dataset`. Readers need only the ``status`` and ``file`` columns (``split`` and
``sha256`` when present): a row is usable when its status is ``complete`` and it names a file.
``labrig groundtruth`` and ``labrig evaluate`` also take one recording given alone
(:func:`open_data`).

Every check (no such folder, no manifest, nothing complete in a split, recordings missing, no
ground truth yet) is one :class:`DatasetError` that says what to give or run instead.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from labrig.errors import LabrigError

MANIFEST_NAME = "manifest.csv"
MANIFEST_COLUMNS: tuple[str, ...] = (
    "id", "index", "indenter", "x_mm", "y_mm", "depth_mm", "force_n", "normal_speed_mm_s", "shear_direction_deg",
    "shear_mm", "shear_speed_mm_s", "wait_s", "repetition", "split", "status", "reason", "file", "sha256", "duration_s",
    "made_by", "fell_behind")
SPLITS: tuple[str, ...] = ("train", "val", "test")
#: The ``split`` that selects every split.
ALL_SPLITS = "all"
COMPLETE = "complete"
RECORDING_SUFFIX = ".h5"
SIDECAR_SUFFIX = ".gt.h5"
EVENTS_SIDECAR_SUFFIX = ".events.toml"
_NAMES_LISTED = 3  # recordings named one by one in an error message


class DatasetError(LabrigError):
    """A campaign folder or recording cannot be used as given; the message says what to give or run."""


def sidecar_path(recording: str | Path) -> Path:
    """The ground-truth sidecar ``NAME.gt.h5`` beside the recording ``NAME.h5``."""
    path = Path(recording)
    stem = path.name[: -len(RECORDING_SUFFIX)] if path.name.endswith(RECORDING_SUFFIX) else path.name
    return path.with_name(f"{stem}{SIDECAR_SUFFIX}")


def events_sidecar_path(recording: str | Path) -> Path:
    """The contrast-threshold calibration ``NAME.events.toml`` of the camera that made ``NAME.h5``, beside it."""
    path = Path(recording)
    stem = path.name[: -len(RECORDING_SUFFIX)] if path.name.endswith(RECORDING_SUFFIX) else path.name
    return path.with_name(f"{stem}{EVENTS_SIDECAR_SUFFIX}")


def read_manifest(path: Path) -> list[dict[str, str]]:
    """A manifest's rows (column -> text) in file order; a :class:`DatasetError` if it lacks status/file."""
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    if rows and not {"status", "file"} <= set(rows[0]):
        raise DatasetError(f"{path} lacks the status/file columns of a campaign manifest")
    return rows


def write_manifest(path: Path, rows: Iterable[Mapping[str, str]]) -> None:
    """Write ``rows`` (every one with all of :data:`MANIFEST_COLUMNS`) atomically: a temporary file renamed over ``path``."""
    temporary = path.with_suffix(".csv.tmp")
    with temporary.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=MANIFEST_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    os.replace(temporary, path)


@dataclass(frozen=True)
class DatasetRecording:
    """One recording to use: a complete row of a manifest, or a recording file given alone."""

    path: Path
    split: str = ""  # the manifest's split; "" for a recording given alone
    sha256: str = ""  # the manifest's SHA-256 of the file; "" when unknown

    @property
    def sidecar(self) -> Path:
        """Its ground truth, ``NAME.gt.h5`` (which may not exist yet)."""
        return sidecar_path(self.path)


class Dataset:
    """A campaign output folder (see the module docstring); reading it re-reads the manifest."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    @classmethod
    def open(cls, folder: str | Path) -> Dataset:
        """An existing campaign folder with its manifest; a :class:`DatasetError` saying what to give otherwise."""
        return cls._open(Path(folder), recording_ok=False)

    @classmethod
    def _open(cls, folder: Path, *, recording_ok: bool) -> Dataset:
        give = _what_to_give(recording_ok)
        if not folder.exists():
            raise DatasetError(f"{folder}: no such folder; give {give}")
        if folder.is_file():
            raise DatasetError(f"{folder} is a file; give {give}")
        dataset = cls(folder)
        if not dataset.manifest_path.exists():
            raise DatasetError(f"{folder} has no {MANIFEST_NAME}: give {give}")
        return dataset

    @property
    def manifest_path(self) -> Path:
        return self.folder / MANIFEST_NAME

    def recording_path(self, recording_id: str) -> Path:
        """Where the campaign writes the recording ``recording_id``: ``ID.h5`` in the folder."""
        return self.folder / f"{recording_id}{RECORDING_SUFFIX}"

    def rows(self) -> list[dict[str, str]]:
        """The manifest's rows as read (see :func:`read_manifest`)."""
        return read_manifest(self.manifest_path)

    def complete(self, split: str = ALL_SPLITS) -> list[DatasetRecording]:
        """The recordings the manifest lists as complete, in its order: of ``split``, or all of them."""
        return [DatasetRecording(self.folder / row["file"], row.get("split", ""), row.get("sha256", ""))
                for row in self.rows() if _usable(row) and split in (ALL_SPLITS, row.get("split"))]

    def count_not_complete(self) -> int:
        """Rows of the manifest that are not usable recordings (pending, aborted, failed)."""
        return sum(1 for row in self.rows() if not _usable(row))

    def require(self, split: str = ALL_SPLITS) -> list[DatasetRecording]:
        """:meth:`complete`, refusing an empty list."""
        chosen = self.complete(split)
        if not chosen:
            where = "" if split == ALL_SPLITS else f" in the {split!r} split"
            counts: dict[str, int] = {}
            for recording in self.complete():
                counts[recording.split] = counts.get(recording.split, 0) + 1
            found = ", ".join(f"{name or 'no split'} {n}" for name, n in counts.items())
            raise DatasetError(f"{self.manifest_path} lists no complete recording{where}"
                               + (f" (complete by split: {found}; try --split all)" if found else ""))
        return chosen


def open_data(path: str | Path) -> Dataset | DatasetRecording:
    """What ``labrig groundtruth`` and ``labrig evaluate`` take: a campaign folder, or one recording alone."""
    path = Path(path)
    if not path.exists() and path.suffix == RECORDING_SUFFIX:
        raise DatasetError(f"{path}: no such file; give {_what_to_give(recording_ok=True)}")
    if path.is_file():
        if path.name.endswith(SIDECAR_SUFFIX):
            raise DatasetError(f"{path} is a ground-truth sidecar; give the recording it belongs to")
        return DatasetRecording(path)
    return Dataset._open(path, recording_ok=True)


def require_present(recordings: Sequence[DatasetRecording], data: str | Path) -> None:
    """Refuse recordings a manifest lists that are not in the folder ``data``."""
    missing = [r.path.name for r in recordings if not r.path.exists()]
    if missing:
        raise DatasetError(f"{data}: recordings listed in the manifest are missing: {_names(missing)}")


def require_groundtruth(recordings: Sequence[DatasetRecording], data: str | Path) -> None:
    """Refuse recordings without their sidecar, naming the command that makes them for ``data``."""
    missing = [r.path.name for r in recordings if not r.sidecar.exists()]
    if missing:
        raise DatasetError(f"{data}: no ground truth for {_names(missing)}; run `labrig groundtruth {data}` first")


def _usable(row: Mapping[str, str]) -> bool:
    return row.get("status") == COMPLETE and bool(row.get("file"))


def _what_to_give(recording_ok: bool) -> str:
    folder = f"a campaign output folder (with {MANIFEST_NAME}, from `labrig campaign ... --out`)"
    return f"{folder} or a single recording file" if recording_ok else folder


def _names(names: Sequence[str]) -> str:
    more = f" and {len(names) - _NAMES_LISTED} more" if len(names) > _NAMES_LISTED else ""
    return ", ".join(names[:_NAMES_LISTED]) + more
