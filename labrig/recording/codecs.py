"""Compression codecs for recording streams, as h5py dataset keyword arguments.

``gzip`` and ``lzf`` are built into h5py; the others come from hdf5plugin, whose
import registers the filters with HDF5. A reader of a file written with an
hdf5plugin codec must ``import hdf5plugin`` too (labrig's reader does).
tools/bench/bench_writer.py measures them side by side.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal

import hdf5plugin

#: The codec for bulk streams (camera events), chosen by tools/bench/bench_writer.py.
DEFAULT_BULK_CODEC = "bitshuffle-lz4"
#: The codec for every other stream: small, and readable by any HDF5 reader.
PORTABLE_CODEC = "gzip"
#: The codec for the virtual rig's truth streams (1 kHz marker positions, depth maps: most of a
#: virtual recording's bytes), chosen by tools/bench/bench_truth_codecs.py: Blosc2's LZ4 after a
#: byte shuffle (which groups the floats' sign-and-exponent and high mantissa bytes) writes them
#: 1.75x faster than zstd, reads them 1.35x faster and stores 11 % fewer bytes (paper-003).
TRUTH_CODEC = "blosc2-lz4-shuffle"


def _blosc2(cname: Literal["lz4", "zstd"], clevel: int, shuffle: int = hdf5plugin.Blosc2.BITSHUFFLE) -> dict[str, Any]:
    return dict(hdf5plugin.Blosc2(cname=cname, clevel=clevel, filters=shuffle))


CODECS: dict[str, Callable[[], dict[str, Any]]] = {
    "none": lambda: {},
    "gzip": lambda: {"compression": "gzip", "compression_opts": 4, "shuffle": True},
    "lzf": lambda: {"compression": "lzf", "shuffle": True},
    "zstd": lambda: dict(hdf5plugin.Zstd(clevel=3)),
    "lz4": lambda: dict(hdf5plugin.LZ4()),
    "bitshuffle-lz4": lambda: dict(hdf5plugin.Bitshuffle(cname="lz4")),
    "blosc2-lz4": lambda: _blosc2("lz4", 5),
    "blosc2-zstd": lambda: _blosc2("zstd", 3),
    "blosc2-lz4-shuffle": lambda: _blosc2("lz4", 9, hdf5plugin.Blosc2.SHUFFLE),
}


def codec_kwargs(name: str) -> dict[str, Any]:
    """h5py ``create_dataset`` keyword arguments for a codec name."""
    try:
        return CODECS[name]()
    except KeyError:
        known = ", ".join(CODECS)
        raise ValueError(f"unknown codec {name!r}; choose one of: {known}") from None
