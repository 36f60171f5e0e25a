"""Decoder state slots and the skip log, shared by the numba word loops (imports numba).

A decoder's whole state is one int64 array (slots below), so a stream can stop at any word
and resume with the next chunk. Skipped words are logged as runs (byte offset of the first
word, number of words, reason); consecutive skipped words with one reason extend the open run.
"""

from __future__ import annotations

from numba import njit

# State slots (int64 array of N_SLOTS).
STARTED = 0  # 1 once the first TIME_HIGH was seen
BASE = 1  # current time base, absolute us (time-high loops included)
LOOPS = 2  # time-high loops counted
TIME = 3  # current event time, absolute us (EVT3)
Y = 4  # current row (EVT3)
XBASE = 5  # vector base x (EVT3)
POL = 6  # vector polarity (EVT3)
CD = 7  # 1: ADDR_Y mode (CD events), 0: EM_Y mode (EVT3)
GROUP = 8  # 1 while inside an OTHERS/IMU + CONTINUED group
RUN_OFF = 9  # open skip run: byte offset of its first word
RUN_LEN = 10  # open skip run: words (0: no open run)
RUN_REASON = 11  # open skip run: reason
N_RUNS = 12  # skip runs closed so far (may exceed the log's capacity; only the first ones are kept)
SKIPPED = 13  # skipped words in total
DROPPED = 14  # events dropped for lying outside the geometry
OTHERS = 15  # OTHERS / IMU / CONTINUED words consumed (not events)
WORD_OFF = 16  # byte offset in the stream of words[0] of the current call
N_SLOTS = 17

# Skip reasons.
BEFORE_TIME_HIGH = 1
UNKNOWN_TYPE = 2
ORPHAN_CONTINUED = 3
OUT_OF_GEOMETRY = 4
TRUNCATED = 5


@njit(cache=True, nogil=True)
def flush_run(state, runs):
    """Close the open skip run into ``runs`` (int64 [k, 3]: offset, words, reason) if there is room."""
    if state[RUN_LEN] > 0:
        k = state[N_RUNS]
        if k < runs.shape[0]:
            runs[k, 0] = state[RUN_OFF]
            runs[k, 1] = state[RUN_LEN]
            runs[k, 2] = state[RUN_REASON]
        state[N_RUNS] = k + 1
        state[RUN_LEN] = 0


@njit(cache=True, nogil=True)
def skip(state, runs, offset, reason, word_bytes):
    """Count the word at byte ``offset`` as skipped for ``reason``."""
    state[SKIPPED] += 1
    if state[RUN_LEN] > 0 and state[RUN_REASON] == reason and state[RUN_OFF] + state[RUN_LEN] * word_bytes == offset:
        state[RUN_LEN] += 1
    else:
        flush_run(state, runs)
        state[RUN_OFF] = offset
        state[RUN_LEN] = 1
        state[RUN_REASON] = reason
