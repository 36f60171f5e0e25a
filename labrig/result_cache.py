"""Task results on disk: one ``.npz`` per result, keyed by the function, its version, the inputs and their files.

Layout: ``cache_dir/<module.function>/<key>.npz``; ``key`` = SHA-256 (:func:`labrig.cache.cache_key`) of

* :data:`CACHE_FORMAT` (bumped when the stored form changes), the function's qualified name
  and its ``cache_version`` attribute (bump it when the function's results change; code
  changes are not detected otherwise);
* the task's inputs as canonical JSON (``1`` and ``1.0`` are different inputs);
* for every string input naming an existing file: its size, modification time (ns) and a
  sampled BLAKE2 hash (the first and last 64 KiB and 16 evenly spaced 64 KiB blocks, so at
  most 1.1 MiB read even for a recording of hundreds of MB), and the same of the files that
  decide how it is read (:data:`COMPANIONS`: a depth network's model card beside its ``.onnx``);
  for an existing directory: the name, size and mtime of each file directly in it.

A result is a frozen dataclass (or a dict) of numbers, strings, None, numpy arrays, lists,
and dicts and dataclasses of them: arrays are stored as ``.npz`` members, the rest as one JSON
member (``allow_pickle=False``); a dataclass is stored with its class's import path and
rebuilt from it (its ``init`` fields; tuple fields as tuples ; tuples elsewhere come back as lists). An entry is
written to a temporary file and renamed into place, so an interrupted run never leaves a
corrupt entry; an unreadable one (or one whose class no longer fits) counts as a miss.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import os
import time
import uuid
import warnings
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from labrig.cache import cache_key

#: The stored form; 2: dataclass results.
CACHE_FORMAT = 2
SAMPLE_BLOCK_BYTES = 64 * 1024
SAMPLE_BLOCKS = 16
#: Files beside an input file that decide what it means, by the input's suffix: a depth network's card (its inputs,
#: their integrator's settings, the gates) changes its results as much as its weights do.
COMPANIONS = {".onnx": (".json",)}
_ARRAY = "__array__"
_DATACLASS = "__dataclass__"
_FIELDS = "fields"


class ResultCache:
    """Results of one function on disk, one ``KEY.npz`` each: arrays as members, the rest as JSON."""

    def __init__(self, root: str | Path, fn: Callable[..., Any]) -> None:
        self.name = f"{fn.__module__}.{fn.__qualname__}"
        self.version = str(getattr(fn, "cache_version", ""))
        self.folder = Path(root) / self.name

    def key(self, inputs: dict[str, Any], memo: dict[tuple[str, int, int], str] | None = None) -> str:
        """SHA-256 (hex) of the format, the function, its version, the inputs and the inputs' files."""
        files: dict[str, Any] = {}
        for text in _strings(inputs):
            if "\n" in text or len(text) > 4096 or not text:
                continue
            if os.path.isfile(text):
                files[text] = file_fingerprint(text, memo)
                for suffix in COMPANIONS.get(Path(text).suffix, ()):
                    companion = str(Path(text).with_suffix(suffix))
                    if os.path.isfile(companion):
                        files[companion] = file_fingerprint(companion, memo)
            elif os.path.isdir(text):
                files[text] = _directory_fingerprint(text)
        return cache_key([CACHE_FORMAT, self.name, self.version, inputs, files], digits=64)

    def path(self, key: str) -> Path:
        return self.folder / f"{key}.npz"

    def load(self, key: str) -> Any | None:
        """The stored result, or None (absent or unreadable: an unreadable entry is removed)."""
        path = self.path(key)
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files if name != "__json__"}
                document = json.loads(str(data["__json__"]))
            return _decode(document["result"], arrays)
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile,  # JSONDecodeError is a ValueError
                ImportError, AttributeError, TypeError):  # a result class moved, renamed or changed its fields
            path.unlink(missing_ok=True)
            return None

    def save(self, key: str, result: Any, inputs: dict[str, Any]) -> None:
        """Store atomically (temporary file, then rename); a result that is not plain data is not cached."""
        arrays: dict[str, np.ndarray] = {}
        try:
            encoded = _encode(result, arrays)
        except TypeError as exc:
            warnings.warn(f"{self.name}: result not cached ({exc})", stacklevel=3)
            return
        document = {"function": self.name, "version": self.version, "inputs": inputs, "result": encoded,
                    "saved_unix_s": time.time()}
        self.folder.mkdir(parents=True, exist_ok=True)
        temporary = self.folder / f".{key}.{uuid.uuid4().hex}.tmp"
        try:
            with open(temporary, "wb") as f:
                np.savez(f, allow_pickle=True, __json__=np.array(json.dumps(document)), **arrays)
            os.replace(temporary, self.path(key))
        finally:
            temporary.unlink(missing_ok=True)


# -- the inputs' files ------------------------------------------------------------------------------


def file_fingerprint(path: str | Path, memo: dict[tuple[str, int, int], str] | None = None) -> str:
    """Size, mtime (ns) and a sampled BLAKE2 hash of a file (see the module docstring)."""
    stat = os.stat(path)
    memo_key = (os.path.abspath(path), stat.st_size, stat.st_mtime_ns)
    if memo is not None and memo_key in memo:
        return memo[memo_key]
    digest = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        if stat.st_size <= SAMPLE_BLOCK_BYTES * (SAMPLE_BLOCKS + 2):
            digest.update(f.read())
        else:
            last = stat.st_size - SAMPLE_BLOCK_BYTES
            for offset in np.linspace(0, last, SAMPLE_BLOCKS + 2).astype(np.int64):
                f.seek(int(offset))
                digest.update(f.read(SAMPLE_BLOCK_BYTES))
    text = f"{stat.st_size}:{stat.st_mtime_ns}:{digest.hexdigest()}"
    if memo is not None:
        memo[memo_key] = text
    return text


def _directory_fingerprint(path: str) -> list[list[Any]]:
    entries = []
    with os.scandir(path) as scan:
        for entry in scan:
            if entry.is_file():
                stat = entry.stat()
                entries.append([entry.name, stat.st_size, stat.st_mtime_ns])
    return sorted(entries)


def _strings(value: Any) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, list):
        return [s for v in value for s in _strings(v)]
    if isinstance(value, dict):
        return [s for v in value.values() for s in _strings(v)]
    return []


# -- the stored form --------------------------------------------------------------------------------


def _encode(value: Any, arrays: dict[str, np.ndarray]) -> Any:
    """JSON-able form of a result; arrays go to ``arrays`` and are referenced as {"__array__": name}."""
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            raise TypeError("object arrays cannot be cached")
        name = f"a{len(arrays)}"
        arrays[name] = value
        return {_ARRAY: name}
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        cls = type(value)
        return {_DATACLASS: f"{cls.__module__}:{cls.__qualname__}",
                _FIELDS: {f.name: _encode(getattr(value, f.name), arrays) for f in dataclasses.fields(value) if f.init}}
    if isinstance(value, list | tuple):
        return [_encode(v, arrays) for v in value]
    if isinstance(value, Mapping):
        if not all(isinstance(k, str) for k in value):
            raise TypeError("result dict keys must be strings")
        if _ARRAY in value or _DATACLASS in value:
            raise TypeError(f"'{_ARRAY}' and '{_DATACLASS}' are reserved in cached results")
        return {k: _encode(v, arrays) for k, v in value.items()}
    raise TypeError(f"a {type(value).__name__} is not plain result data")


def _decode(value: Any, arrays: Mapping[str, np.ndarray]) -> Any:
    if isinstance(value, dict):
        if set(value) == {_ARRAY}:
            return arrays[value[_ARRAY]]
        if set(value) == {_DATACLASS, _FIELDS}:
            return _rebuild(value[_DATACLASS], {k: _decode(v, arrays) for k, v in value[_FIELDS].items()})
        return {k: _decode(v, arrays) for k, v in value.items()}
    if isinstance(value, list):
        return [_decode(v, arrays) for v in value]
    return value


def _rebuild(path: str, values: dict[str, Any]) -> Any:
    """An instance of the dataclass at ``module:qualname`` from its fields' values (tuple fields as tuples)."""
    module, _, qualname = path.partition(":")
    cls: Any = importlib.import_module(module)
    for part in qualname.split("."):
        cls = getattr(cls, part)
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise TypeError(f"{path} is not a dataclass")
    tuples = {f.name for f in dataclasses.fields(cls) if str(f.type).startswith(("tuple", "Tuple"))}
    return cls(**{k: tuple(v) if k in tuples and isinstance(v, list) else v for k, v in values.items()})
