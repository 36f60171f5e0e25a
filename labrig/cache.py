"""labrig's on-disk cache: where it lives, how its entries are keyed, and file digests.

Everything expensive and reproducible (contact tables, inverse-FEM operators, ground-truth
depth tables, evaluation results) is cached under one root: ``$LABRIG_CACHE`` when set,
else ``~/.cache/labrig``, one folder per kind (``contact_tables``, ``ifem``,
``groundtruth_tables``, ``eval``). An entry is named by :func:`cache_key` of everything
it was computed from, so a changed input is a new entry, never a stale one.

Standard library only: every layer may use it.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

#: The environment variable that moves the cache root.
CACHE_ENV = "LABRIG_CACHE"
#: Hex digits of a :func:`cache_key` (80 bits).
KEY_DIGITS = 20
_BLOCK_BYTES = 1 << 20


def cache_root() -> Path:
    """``$LABRIG_CACHE``, else ``~/.cache/labrig``."""
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "labrig")


def cache_folder(kind: str, root: str | Path | None = None) -> Path:
    """The folder of one kind of entry: ``root/kind``, ``root`` defaulting to :func:`cache_root`."""
    return Path(root or cache_root()) / kind


def cache_key(spec: object, digits: int = KEY_DIGITS) -> str:
    """The first ``digits`` hex digits of the SHA-256 of ``spec`` as canonical JSON (keys sorted).

    ``spec`` holds every input of the cached computation, plain JSON values only; ``1`` and
    ``1.0`` are different inputs."""
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:digits]


def sha256_of(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(_BLOCK_BYTES), b""):
            digest.update(block)
    return digest.hexdigest()
