"""EVT 2.0: streaming decoder and encoder (32-bit words, 34-bit time).

Encoder contract (events.md section 2): the minimal canonical stream, a TIME_HIGH (t >> 6)
only when it changes, then one CD_OFF / CD_ON or EXT_TRIGGER (5-bit id) word per item with
the 6 low time bits. The decoded times equal the input times (a first time past 2^34 us
climbs from TIME_HIGH 0 through whole loops).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.devices.raw.encode import check_inputs, run_encoder
from labrig.devices.raw.stream import StreamDecoder


class Evt2Decoder(StreamDecoder):
    """Streaming EVT 2.0 decoder (see :class:`StreamDecoder`)."""

    word_bytes = 4
    word_dtype = "<u4"
    max_events_per_word = 1

    @staticmethod
    def _load_kernel() -> Callable[..., tuple[int, int, int]]:
        from labrig.devices.raw import _evt2_kernels

        return _evt2_kernels.decode


def encode_evt2(
    events: npt.NDArray[Any], triggers: npt.NDArray[Any] | None = None, *, width: int = 1280, height: int = 720
) -> bytes:
    """EVT2 payload (no header) for ``events`` (fields x, y, p, t in us) and ``triggers`` (fields p, t, id)."""
    from labrig.devices.raw import _evt2_kernels as K

    ev, tr = check_inputs(events, triggers, width, height, max_trigger_id=31)
    n, m = ev[0].size, tr[0].size
    guess = 2 * (n + m) + 64
    return run_encoder(K.encode, (*ev, *tr), guess, np.uint32).astype("<u4", copy=False).tobytes()
