"""Shared encoder plumbing: input checks and running a word loop into a buffer of the right size."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.devices.raw.stream import TRIGGER_DTYPE

Columns = tuple[npt.NDArray[Any], ...]


def check_inputs(
    events: npt.NDArray[Any], triggers: npt.NDArray[Any] | None, width: int, height: int, max_trigger_id: int
) -> tuple[Columns, Columns]:
    """Validate events (fields x, y, p, t) and triggers (fields p, t, id); return their columns.

    Raises ValueError naming the first offending item: a pixel outside width x height, a
    polarity or trigger value other than 0/1, a negative time, a trigger id above the format's.
    """
    if not 0 < width <= 2048 or not 0 < height <= 2048:
        raise ValueError(f"geometry {width}x{height} outside 1..2048 (11-bit coordinates)")
    events = np.asarray(events)
    if triggers is None:
        triggers = np.zeros(0, TRIGGER_DTYPE)
    triggers = np.asarray(triggers)
    for arr, fields, what in ((events, ("x", "y", "p", "t"), "events"), (triggers, ("p", "t", "id"), "triggers")):
        names = arr.dtype.names or ()
        missing = [f for f in fields if f not in names]
        if missing or arr.ndim != 1:
            raise ValueError(f"{what} must be a 1-D structured array with fields {fields}; missing {missing}")
    ev = tuple(_int_column(events, f) for f in ("x", "y", "p", "t"))
    tr = tuple(_int_column(triggers, f) for f in ("p", "t", "id"))
    _first_bad(ev[0] >= width, "event x >= width", ev[0])
    _first_bad(ev[1] >= height, "event y >= height", ev[1])
    for col, name in ((ev[0], "x"), (ev[1], "y"), (ev[2], "p"), (ev[3], "t")):
        _first_bad(col < 0, f"negative event {name}", col)
    _first_bad(ev[2] > 1, "event p not 0/1", ev[2])
    _first_bad(tr[0] > 1, "trigger p not 0/1", tr[0])
    _first_bad(tr[0] < 0, "trigger p not 0/1", tr[0])
    _first_bad(tr[1] < 0, "negative trigger t", tr[1])
    _first_bad((tr[2] < 0) | (tr[2] > max_trigger_id), f"trigger id outside 0..{max_trigger_id}", tr[2])
    return ev, tr


def run_encoder(kernel: Callable[..., int], args: tuple[Any, ...], guess: int, dtype: type) -> npt.NDArray[Any]:
    """Run ``kernel(*args, out, err)``; if it needs more words than ``guess``, run it again with the size it asked for."""
    out: npt.NDArray[Any] = np.empty(max(int(guess), 16), dtype)
    err = np.zeros(2, np.int64)
    k = kernel(*args, out, err)
    if k > out.shape[0]:
        out = np.empty(k, dtype)
        k = kernel(*args, out, err)
    if k < 0:
        what = "event" if err[0] == 1 else "trigger"
        raise ValueError(
            f"{what} {int(err[1])}: time goes back across a time-high wrap or too far to be told from one; "
            "RAW streams only allow small backward steps"
        )
    return out[:k]


def _int_column(arr: npt.NDArray[Any], name: str) -> npt.NDArray[Any]:
    col = arr[name]
    if not np.issubdtype(col.dtype, np.integer) and not np.issubdtype(col.dtype, np.bool_):
        raise ValueError(f"field {name!r} must be integer, not {col.dtype}")
    if col.dtype == np.bool_:
        col = col.astype(np.uint8)
    elif col.dtype.byteorder not in ("=", "|", "<"):
        col = col.astype(col.dtype.newbyteorder("="))
    return col


def _first_bad(mask: npt.NDArray[np.bool_], what: str, col: npt.NDArray[Any]) -> None:
    if mask.size and mask.any():
        i = int(np.argmax(mask))
        raise ValueError(f"{what} at index {i} (value {col[i]})")
