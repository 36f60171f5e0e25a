"""Where things live in a recording file, and creating that structure.

SWMR forbids new datasets and attributes once writing starts, so every group,
dataset and attribute a recording will need is created here, up front.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from labrig.recording import schema
from labrig.recording.codecs import PORTABLE_CODEC, codec_kwargs

PARTIAL_SUFFIX = ".partial"


def partial_path(path: Path) -> Path:
    """The file a recording is written to until it is finalized."""
    return path.with_name(path.name + PARTIAL_SUFFIX)


def final_path(partial: Path) -> Path:
    """The finalized name of a ``NAME.partial`` file."""
    if partial.name.endswith(PARTIAL_SUFFIX):
        return partial.with_name(partial.name[: -len(PARTIAL_SUFFIX)])
    return partial


def stream_path(name: str) -> str:
    """HDF5 path of a stream: ``/truth/...`` for sim truth, else ``/streams/NAME``."""
    return name if name.startswith("truth/") else f"streams/{name}"


def stream_group(f: h5py.File | h5py.Group, name: str) -> h5py.Group:
    return f[stream_path(name)]


def create_layout(
    f: h5py.File,
    specs: Iterable[schema.StreamSpec],
    root_attrs: dict[str, Any],
    calibration: dict[str, str],
    bulk_codec: str,
) -> None:
    """Create every group, dataset and attribute of an empty recording."""
    specs = tuple(specs)
    for key, value in root_attrs.items():
        f.attrs[key] = value
    f.create_group("truth")
    cal = f.create_group("calibration")
    for name, text in calibration.items():
        cal.attrs[name] = text
    clock = f.create_group("clock")
    for device in schema.CLOCK_SOURCES:
        clock.create_group(device)
    for spec in specs:
        _create_stream(f, spec, bulk_codec)
    events = f[stream_path("events")]
    events.create_dataset(
        "index_first_row", shape=(0,), maxshape=(None,), dtype="<i8", chunks=(4096,), **codec_kwargs(PORTABLE_CODEC)
    )
    events.create_dataset("index_start_bin", data=np.array([-1], dtype="<i8"))
    events.attrs["index_bin_us"] = schema.EVENT_INDEX_BIN_US
    commits = f.create_group(schema.COMMITS_PATH)
    commits.attrs["streams"] = [s.name for s in specs]
    commits.attrs["description"] = "row counts of every stream after each complete flush; trust no row beyond the last"
    commits.create_dataset("t_host_us", shape=(0,), maxshape=(None,), dtype="<i8", chunks=(256,))
    commits.create_dataset("rows", shape=(0, len(specs)), maxshape=(None, len(specs)), dtype="<i8", chunks=(256, len(specs)))


def _create_stream(f: h5py.File, spec: schema.StreamSpec, bulk_codec: str) -> None:
    group = f.create_group(stream_path(spec.name))
    group.attrs["description"] = spec.description
    group.attrs["clock"] = spec.clock or "host"
    for key, value in spec.attrs.items():
        group.attrs[key] = value
    codec = spec.codec or (bulk_codec if spec.bulk else PORTABLE_CODEC)
    for column in spec.columns:
        ds = group.create_dataset(
            column.name,
            shape=(0, *column.shape),
            maxshape=(None, *column.shape),
            dtype=column.np_dtype,
            chunks=(spec.chunk_rows, *column.shape),
            **codec_kwargs(codec),
        )
        ds.attrs["unit"] = column.unit
        ds.attrs["description"] = column.description
