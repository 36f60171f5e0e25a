"""EVT 3.0: streaming decoder and encoder (16-bit words, 24-bit time, vectors).

Encoder contract (events.md sections 1 and 10): the payload starts with TIME_HIGH then
TIME_LOW; every TIME_HIGH step is written (the sensor's 4096 us cadence, so a 24-bit wrap shows
as 4095 -> 0), and TIME_HIGH is repeated after ``time_high_every`` words of one step; a
TIME_LOW follows every TIME_HIGH; ADDR_Y when the row changes; runs of at least
``vector_min`` events with one time, row and polarity inside one 32-aligned block (base + 32 <=
width) become VECT_BASE_X + VECT_12 + VECT_12 + VECT_8, other events ADDR_X; triggers are
EXT_TRIGGER words (4-bit id). The decoded times equal the input times, wraps included: a
stream whose first time is past 2^24 us starts with TIME_HIGH 0 and climbs through whole
loops (4095 -> 0) before its first event.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.devices.raw.encode import check_inputs, run_encoder
from labrig.devices.raw.stream import StreamDecoder

#: Default repeat of an unchanged TIME_HIGH, in words (a real Gen4.1 stream repeats every ~540).
TIME_HIGH_EVERY = 512
#: Default smallest run written as a vector triplet (4 words); shorter runs are ADDR_X words.
VECTOR_MIN = 5
#: Words, evenly spread, that a decode's buffer is sized on; when they hold more than CAPACITY_COUNT_ABOVE events a
#: word, all the words are counted.
CAPACITY_SAMPLE_WORDS = 65_536
CAPACITY_COUNT_ABOVE = 0.9


class Evt3Decoder(StreamDecoder):
    """Streaming EVT 3.0 decoder (see :class:`StreamDecoder`)."""

    word_bytes = 2
    word_dtype = "<u2"
    max_events_per_word = 12

    @staticmethod
    def _load_kernel() -> Callable[..., tuple[int, int, int]]:
        from labrig.devices.raw import _evt3_kernels

        return _evt3_kernels.decode

    def _capacity(self, words: npt.NDArray[Any]) -> int:
        """Events buffer for ``words``: the word count while an even sample of them holds fewer events than words,
        else the events they hold at most (a pass that counts them), so that a vector-rich stream's word loop fills
        one buffer instead of growing a second and joining the two."""
        from labrig.devices.raw import _evt3_kernels

        n_words = int(words.shape[0])
        stride = max(1, n_words // CAPACITY_SAMPLE_WORDS)
        estimate = int(_evt3_kernels.count_events(words[::stride])) * stride  # a word's count needs no other word
        if estimate <= CAPACITY_COUNT_ABOVE * n_words:
            return n_words + 64
        return int(_evt3_kernels.count_events(words)) + 64


def encode_evt3(
    events: npt.NDArray[Any],
    triggers: npt.NDArray[Any] | None = None,
    *,
    width: int = 1280,
    height: int = 720,
    time_high_every: int = TIME_HIGH_EVERY,
    vector_min: int = VECTOR_MIN,
) -> bytes:
    """EVT3 payload (no header) for ``events`` (fields x, y, p, t in us) and ``triggers`` (fields p, t, id).

    ``vector_min`` = 0 writes no vectors. Times may step back a little (as merged sensor
    sources do) but not across a 24-bit wrap nor by 4085 TIME_HIGH steps (ValueError).
    """
    from labrig.devices.raw import _evt3_kernels as K

    if vector_min and not 2 <= vector_min <= 32:
        raise ValueError("vector_min must be 0 (no vectors) or 2..32")
    if time_high_every < 1:
        raise ValueError("time_high_every must be >= 1")
    ev, tr = check_inputs(events, triggers, width, height, max_trigger_id=15)
    n, m = ev[0].size, tr[0].size
    t_max = max(int(ev[3].max()) if n else 0, int(tr[1].max()) if m else 0)
    guess = 3 * n + 3 * m + (t_max >> 12) + 2 * (n + m) // time_high_every + 64
    args = (*ev, *tr, int(width), int(time_high_every), int(vector_min))
    return run_encoder(K.encode, args, guess, np.uint16).astype("<u2", copy=False).tobytes()
