"""Streaming word decoder: feed bytes in any chunks, get events and triggers as they decode.

A chunk may end inside a word (the partial bytes wait for the next chunk) or inside a group of
words (vector triplet, TIME_HIGH/TIME_LOW, OTHERS + CONTINUED): every piece of decoding state
lives in one int64 array that the numba word loop updates, so splitting the input anywhere
gives exactly what one call gives. The format-specific word loops live in ``_evt3_kernels`` /
``_evt2_kernels`` and are imported (numba) on the first decode.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from labrig.eventtypes import EVENT_DTYPE

#: One CD event (the same dtype as labrig.sim.events / labrig.recording.reader).
#: One external-trigger edge: p value (1 rising, 0 falling), t (us), channel id.
TRIGGER_DTYPE = np.dtype([("p", "u1"), ("t", "<i8"), ("id", "u1")])
#: One run of skipped words: byte offset of its first word in the stream, words, reason (SkipReason).
SKIP_DTYPE = np.dtype([("offset", "<i8"), ("words", "<i8"), ("reason", "u1")])

#: Runs of skipped words kept per decoder (all skipped words are counted).
MAX_SKIP_RUNS = 10_000

_TRIGGERS_FIRST = 256  # first trigger buffer; it doubles when full


class SkipReason(IntEnum):
    """Why words were skipped."""

    BEFORE_TIME_HIGH = 1  # before the first TIME_HIGH (as Prophesee's standalone decoders do)
    UNKNOWN_TYPE = 2  # a word type the format does not define (or IMU in EVT3)
    ORPHAN_CONTINUED = 3  # a CONTINUED word not following OTHERS / IMU / CONTINUED
    OUT_OF_GEOMETRY = 4  # the word's event(s) fall outside the sensor; those events are dropped
    TRUNCATED = 5  # a partial word at the end of the stream


@dataclass(frozen=True)
class Decoded:
    """What one ``feed`` / ``finish`` call produced."""

    events: npt.NDArray[Any]
    triggers: npt.NDArray[Any]


class StreamDecoder:
    """Base of the EVT3 / EVT2 decoders: bytes in, structured events and triggers out.

    ``width`` / ``height``: events outside are dropped and logged (None: no limit beyond the
    11-bit coordinates). ``offset``: byte offset in the file of the first byte fed, so the
    skip log gives file offsets.
    """

    word_bytes: ClassVar[int]
    word_dtype: ClassVar[str]
    #: Events one word can produce at most.
    max_events_per_word: ClassVar[int]

    def __init__(self, width: int | None = None, height: int | None = None, offset: int = 0) -> None:
        if sys.byteorder != "little":  # pragma: no cover - numba needs native words
            raise RuntimeError("RAW decoding needs a little-endian host")
        from labrig.devices.raw import _state

        self._S = _state
        self.width = 2048 if width is None else int(width)
        self.height = 2048 if height is None else int(height)
        self.state = np.zeros(_state.N_SLOTS, np.int64)
        self.state[_state.CD] = 1
        self.state[_state.RUN_OFF] = -1
        self._runs = np.zeros((MAX_SKIP_RUNS, 3), np.int64)
        self._pending = b""
        self._scratch = np.empty(0, np.uint8)
        self._offset = int(offset)  # file offset of the next byte to be fed
        self._finished = False
        self._kernel = self._load_kernel()

    # -- to be provided by the format -------------------------------------------------------
    @staticmethod
    def _load_kernel() -> Callable[..., tuple[int, int, int]]:  # pragma: no cover - abstract
        raise NotImplementedError

    # -- feeding ------------------------------------------------------------------------------
    def feed(self, data: bytes | bytearray | memoryview | npt.NDArray[Any]) -> Decoded:
        """Decode the next bytes of the stream (any length); returns the events and triggers completed."""
        if self._finished:
            raise RuntimeError("feed() after finish()")
        if isinstance(data, np.ndarray):
            data = np.ascontiguousarray(data)
        buf = memoryview(data).cast("B")  # type: ignore[arg-type]
        ws = self.word_bytes
        parts: list[Decoded] = []
        start = 0
        if self._pending:
            need = ws - len(self._pending)
            if len(buf) < need:
                self._pending += bytes(buf)
                self._offset += len(buf)
                return Decoded(np.zeros(0, EVENT_DTYPE), np.zeros(0, TRIGGER_DTYPE))
            word = np.frombuffer(self._pending + bytes(buf[:need]), dtype=self.word_dtype).copy()
            parts.append(self._decode_words(word, self._offset - len(self._pending)))
            self._offset += need
            self._pending = b""
            start = need
        n_words = (len(buf) - start) // ws
        if n_words:
            words = np.frombuffer(buf, dtype=np.uint8, count=n_words * ws, offset=start)
            if not words.flags.writeable or words.ctypes.data % ws:
                # one kind of array for the word loop (numba compiles per kind): writable and aligned
                words = self._scratch_copy(words)
            parts.append(self._decode_words(words.view(self.word_dtype), self._offset))
            self._offset += n_words * ws
        rest = buf[start + n_words * ws :]
        if len(rest):
            self._pending = bytes(rest)
            self._offset += len(rest)
        return _join(parts)

    def finish(self) -> None:
        """End of stream: a partial word left is logged as TRUNCATED and the skip log is closed."""
        if self._finished:
            return
        if self._pending:
            st = self.state
            st[self._S.SKIPPED] += 1
            self._close_run()
            st[self._S.RUN_OFF] = self._offset - len(self._pending)
            st[self._S.RUN_LEN] = 1
            st[self._S.RUN_REASON] = int(SkipReason.TRUNCATED)
            self._pending = b""
        self._close_run()
        self._finished = True

    def decode_all(self, data: bytes | bytearray | memoryview | npt.NDArray[Any]) -> Decoded:
        """``feed(data)`` then ``finish()``: what ``feed`` returned."""
        out = self.feed(data)
        self.finish()
        return out

    # -- reports --------------------------------------------------------------------------------
    @property
    def skipped_words(self) -> int:
        """Words skipped so far (all reasons, a trailing partial word included)."""
        return int(self.state[self._S.SKIPPED])

    @property
    def dropped_events(self) -> int:
        """Events dropped for lying outside the geometry."""
        return int(self.state[self._S.DROPPED])

    @property
    def others_words(self) -> int:
        """OTHERS / IMU / CONTINUED words consumed without producing events."""
        return int(self.state[self._S.OTHERS])

    @property
    def time_high_loops(self) -> int:
        """Time-high wraps counted (24-bit for EVT3, 34-bit for EVT2)."""
        return int(self.state[self._S.LOOPS])

    @property
    def skips(self) -> npt.NDArray[Any]:
        """Runs of skipped words so far (SKIP_DTYPE), at most MAX_SKIP_RUNS, the open run included."""
        S = self.state
        n = min(int(S[self._S.N_RUNS]), MAX_SKIP_RUNS)
        out = np.empty(n + (1 if S[self._S.RUN_LEN] > 0 and n < MAX_SKIP_RUNS else 0), SKIP_DTYPE)
        out["offset"][:n] = self._runs[:n, 0]
        out["words"][:n] = self._runs[:n, 1]
        out["reason"][:n] = self._runs[:n, 2]
        if out.size > n:
            out[n] = (S[self._S.RUN_OFF], S[self._S.RUN_LEN], S[self._S.RUN_REASON])
        return out

    @property
    def skip_runs_total(self) -> int:
        """Runs of skipped words in total (the log keeps the first MAX_SKIP_RUNS)."""
        S = self.state
        return int(S[self._S.N_RUNS]) + (1 if S[self._S.RUN_LEN] > 0 else 0)

    # -- internals ------------------------------------------------------------------------------
    def _scratch_copy(self, data: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
        """``data`` copied into a reused buffer (decoded events never point into it)."""
        if self._scratch.size < data.size:
            self._scratch = np.empty(max(data.size, 2 * self._scratch.size), np.uint8)
        out = self._scratch[: data.size]
        out[:] = data
        return out

    def _close_run(self) -> None:
        S = self._S
        st = self.state
        if st[S.RUN_LEN] > 0:
            k = int(st[S.N_RUNS])
            if k < MAX_SKIP_RUNS:
                self._runs[k] = (st[S.RUN_OFF], st[S.RUN_LEN], st[S.RUN_REASON])
            st[S.N_RUNS] = k + 1
            st[S.RUN_LEN] = 0

    def _decode_words(self, words: npt.NDArray[Any], offset: int) -> Decoded:
        """Decode ``words`` (first word at byte ``offset``)."""
        ev = np.empty(self._capacity(words), EVENT_DTYPE)
        n_first, more, triggers = self._run(words, offset, self.state, self._runs, ev)
        events = _trim(ev, n_first) if not more else np.concatenate([ev[:n_first], *more])
        return Decoded(events, _trim(triggers, triggers.shape[0]))

    def _capacity(self, words: npt.NDArray[Any]) -> int:
        """Events buffer for ``words``: exact for one event per word at most, else a guess (it grows)."""
        n_words = int(words.shape[0])
        return n_words if self.max_events_per_word == 1 else n_words + 64

    def _run(
        self,
        words: npt.NDArray[Any],
        offset: int,
        state: npt.NDArray[np.int64],
        runs: npt.NDArray[np.int64],
        ev: npt.NDArray[Any],
    ) -> tuple[int, list[npt.NDArray[Any]], npt.NDArray[Any]]:
        """The word loop over all ``words`` from ``state``, events into ``ev`` then, if it fills up, into new arrays.

        Returns (events filled in ``ev``, the further event arrays, the triggers).
        """
        state[self._S.WORD_OFF] = offset
        n = words.shape[0]
        more: list[npt.NDArray[Any]] = []
        n_first = -1
        buf = ev
        tr = np.empty(_TRIGGERS_FIRST, TRIGGER_DTYPE)
        pos = n_ev = n_tr = 0
        while True:
            pos, n_ev, n_tr = self._kernel(words, pos, state, self.width, self.height, buf, n_ev, tr, n_tr, runs)
            if pos >= n:
                break
            if n_tr >= tr.shape[0]:
                tr = _grow(tr, n_tr, 2 * tr.shape[0])
            if n_ev + self.max_events_per_word > buf.shape[0]:
                # more events per word than guessed: keep what is filled, size the rest on the rate so far
                if n_first < 0:
                    n_first = n_ev
                else:
                    more.append(_trim(buf, n_ev))
                rate = n_ev / max(pos, 1)
                buf = np.empty(int((n - pos) * min(rate * 1.25 + 0.1, self.max_events_per_word)) + 64, EVENT_DTYPE)
                n_ev = 0
        if n_first < 0:
            n_first = n_ev
        else:
            more.append(_trim(buf, n_ev))
        return n_first, more, tr[:n_tr]


def _trim(arr: npt.NDArray[Any], n: int) -> npt.NDArray[Any]:
    """``arr[:n]``, copied when that frees more than half of the buffer."""
    return arr[:n].copy() if n < arr.shape[0] // 2 else arr[:n]


def _grow(arr: npt.NDArray[Any], n: int, size: int) -> npt.NDArray[Any]:
    out = np.empty(size, arr.dtype)
    out[:n] = arr[:n]
    return out


def _join(parts: list[Decoded]) -> Decoded:
    if not parts:
        return Decoded(np.zeros(0, EVENT_DTYPE), np.zeros(0, TRIGGER_DTYPE))
    if len(parts) == 1:
        return parts[0]
    return Decoded(np.concatenate([p.events for p in parts]), np.concatenate([p.triggers for p in parts]))
