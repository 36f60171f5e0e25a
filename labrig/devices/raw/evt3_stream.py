"""EVT 3.0 for consecutive chunks of one stream: the encoder behind a live EVK4 stream and a RAW export.

:func:`~labrig.devices.raw.evt3.encode_evt3` encodes one self-contained piece; a stream cut into
chunks needs the TIME_HIGH steps between them too, so that a decoder reading the chunks one
after another sees one stream with the absolute camera time preserved.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.devices.raw.evt3 import encode_evt3

#: One TIME_HIGH step of EVT3, us, and the 24-bit loop in steps.
STEP_US = 1 << 12
LOOP_STEPS = 1 << 12
_T_TIME_HIGH = 0x8


class Evt3StreamEncoder:
    """EVT3 for consecutive chunks that decodes as one stream (absolute camera time preserved).

    The first chunk is encoded as a stream start (the encoder climbs through whole 24-bit
    loops when the time is past 2^24 us). Before each later chunk, the TIME_HIGH steps since
    the previous one are written (every step for gaps up to one loop, else a 4095 -> 0 pair per
    loop), then the chunk itself with its time base taken from its first step. Times earlier
    than the time base already sent are raised to it (a real stream cannot go back further).
    """

    def __init__(self, width: int = 1280, height: int = 720) -> None:
        self.width = int(width)
        self.height = int(height)
        self.high = -1  # absolute TIME_HIGH step the decoder holds (-1: stream not started)

    def encode(self, events: npt.NDArray[Any], triggers: npt.NDArray[Any]) -> bytes:
        if events.size == 0 and triggers.size == 0:
            return b""
        t_first = min(int(events["t"].min()) if events.size else 1 << 62, int(triggers["t"].min()) if triggers.size else 1 << 62)
        t_last = max(int(events["t"].max()) if events.size else -1, int(triggers["t"].max()) if triggers.size else -1)
        if self.high < 0:
            payload = encode_evt3(events, triggers, width=self.width, height=self.height)
            self.high = t_last >> 12
            return payload
        floor = self.high * STEP_US
        if t_first < floor:
            events, triggers = _raise_times(events, floor), _raise_times(triggers, floor)
            t_first = floor
        target = t_first >> 12
        bridge = self._bridge(target)
        loop0 = (target // LOOP_STEPS) * LOOP_STEPS * STEP_US
        ev = events.copy()
        ev["t"] -= loop0
        tr = triggers.copy()
        tr["t"] -= loop0
        payload = encode_evt3(ev, tr, width=self.width, height=self.height)
        self.high = max(self.high, t_last >> 12)
        return bridge + payload

    def _bridge(self, target: int) -> bytes:
        """TIME_HIGH words from the step after ``self.high`` up to (not including) ``target``."""
        if target <= self.high + 1:
            return b""
        if target - self.high <= LOOP_STEPS:
            steps = np.arange(self.high + 1, target, dtype=np.int64)
        else:  # a long silence: one 4095 -> 0 pair per loop crossed, then the target's loop
            loops = np.arange(self.high // LOOP_STEPS, target // LOOP_STEPS, dtype=np.int64)
            steps = np.stack([loops * LOOP_STEPS + LOOP_STEPS - 1, (loops + 1) * LOOP_STEPS], axis=1).ravel()
        words = (_T_TIME_HIGH << 12) | (steps & 0xFFF)
        return words.astype("<u2").tobytes()


def _raise_times(arr: npt.NDArray[Any], floor: int) -> npt.NDArray[Any]:
    if arr.size == 0 or int(arr["t"].min()) >= floor:
        return arr
    out = arr.copy()
    np.maximum(out["t"], floor, out=out["t"])
    return out
