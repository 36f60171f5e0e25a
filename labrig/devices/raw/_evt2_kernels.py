"""EVT 2.0 word loops (numba): decode 32-bit words into events, encode events into words.

Decoding follows Prophesee's standalone EVT2 decoder (events.md section 2): words before the
first TIME_HIGH are skipped; t = TIME_HIGH << 6 | the word's 6 time bits; a TIME_HIGH counts
a 34-bit loop when it drops by at least 2^28 - 11 steps. labrig additions: events outside the
geometry are dropped (and logged), OTHERS / IMU + CONTINUED groups are consumed, unknown
types and stray CONTINUED words are logged.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from labrig.devices.raw import _state as S

WORD_BYTES = 4
HIGH_BITS = 28
LOOP_US = 1 << 34
MAX_BASE_US = ((1 << 28) - 1) << 6
LOOP_THRESHOLD_US = 10 << 6
#: TIME_HIGH steps: one loop, the largest raw value, and how far an encoder may go back.
LOOP_STEPS = 1 << 28
MAX_RAW = (1 << 28) - 1
MAX_BACK_STEPS = MAX_RAW - 10 - 1

T_CD_OFF, T_CD_ON, T_TIME_HIGH, T_EXT_TRIGGER, T_IMU, T_OTHERS, T_CONTINUED = 0x0, 0x1, 0x8, 0xA, 0xD, 0xE, 0xF


@njit(cache=True, nogil=True)
def decode(words, pos, state, width, height, ev, n_ev, tr, n_tr, runs):
    """Decode ``words[pos:]`` into ``ev[n_ev:]`` / ``tr[n_tr:]``; stop early when either is full.

    Returns (next word index, events filled, triggers filled); the state is updated in place.
    """
    n = words.shape[0]
    cap_ev = ev.shape[0]
    cap_tr = tr.shape[0]
    base = state[S.BASE]
    loops = state[S.LOOPS]
    group = state[S.GROUP] != 0
    off0 = state[S.WORD_OFF]
    dropped = 0
    others = 0
    i = pos
    while i < n and state[S.STARTED] == 0:
        w = np.int64(words[i])
        if (w >> 28) == T_TIME_HIGH:
            state[S.STARTED] = 1
            base = (w & MAX_RAW) << 6
        else:
            S.skip(state, runs, off0 + i * WORD_BYTES, S.BEFORE_TIME_HIGH, WORD_BYTES)
        i += 1
    while i < n:
        w = np.int64(words[i])
        typ = w >> 28
        in_group = group
        group = False
        if typ <= T_CD_ON:
            if n_ev >= cap_ev:
                break
            x = (w >> 11) & 0x7FF
            y = w & 0x7FF
            if x < width and y < height:
                e = ev[n_ev]
                e.x = x
                e.y = y
                e.p = typ
                e.t = base + ((w >> 22) & 63)
                n_ev += 1
            else:
                dropped += 1
                S.skip(state, runs, off0 + i * WORD_BYTES, S.OUT_OF_GEOMETRY, WORD_BYTES)
        elif typ == T_TIME_HIGH:
            new_base = ((w & MAX_RAW) << 6) + loops * LOOP_US
            if base > new_base and base - new_base >= MAX_BASE_US - LOOP_THRESHOLD_US:
                new_base += LOOP_US
                loops += 1
            base = new_base
        elif typ == T_EXT_TRIGGER:
            if n_tr >= cap_tr:
                break
            r = tr[n_tr]
            r.p = w & 1
            r.id = (w >> 8) & 0x1F
            r.t = base + ((w >> 22) & 63)
            n_tr += 1
        elif typ == T_OTHERS or typ == T_IMU:  # noqa: SIM109 - plain compares in the numba loop
            group = True
            others += 1
        elif typ == T_CONTINUED:
            if in_group:
                group = True
                others += 1
            else:
                S.skip(state, runs, off0 + i * WORD_BYTES, S.ORPHAN_CONTINUED, WORD_BYTES)
        else:
            S.skip(state, runs, off0 + i * WORD_BYTES, S.UNKNOWN_TYPE, WORD_BYTES)
        i += 1
    state[S.BASE] = base
    state[S.LOOPS] = loops
    state[S.GROUP] = 1 if group else 0
    state[S.DROPPED] += dropped
    state[S.OTHERS] += others
    return i, n_ev, n_tr


@njit(cache=True, nogil=True)
def _put(out, k, word):
    if k < out.shape[0]:
        out[k] = word
    return k + 1


@njit(cache=True, nogil=True)
def _time_high(raw):
    return (np.int64(T_TIME_HIGH) << 28) | raw


@njit(cache=True, nogil=True)
def encode(x, y, p, t, tp, tt, tid, out, err):
    """Encode events and triggers into EVT2 words in ``out``: a TIME_HIGH only when t >> 6 changes.

    Items are taken in input order, a trigger before the next event when its time is earlier.
    Returns the number of words the stream needs (more than ``out`` holds: call again with a
    bigger ``out``); -1 with err = (code, index) on a time that goes back too far (see EVT3).
    """
    n = x.shape[0]
    m = tt.shape[0]
    k = 0
    high = np.int64(-1)
    i = 0
    j = 0
    while i < n or j < m:
        is_trigger = j < m and (i >= n or tt[j] < t[i])
        now = np.int64(tt[j]) if is_trigger else np.int64(t[i])
        target = now >> 6
        if high < 0:
            if target >= LOOP_STEPS:  # climb from 0 through whole loops so the absolute time survives
                k = _put(out, k, _time_high(0))
                high = 0
            elif (target & 0xFF) == 0x25:  # first byte '%' would read as a header line
                k = _put(out, k, _time_high(target - 1))
                high = target - 1
            else:
                k = _put(out, k, _time_high(target))
                high = target
        if target > high:
            while (target >> HIGH_BITS) > (high >> HIGH_BITS):
                if (target >> HIGH_BITS) == (high >> HIGH_BITS) + 1 and (high & MAX_RAW) - (target & MAX_RAW) > MAX_BACK_STEPS:
                    break  # the decoder sees this drop as a loop
                top = ((high >> HIGH_BITS) << HIGH_BITS) + MAX_RAW
                if high != top:
                    k = _put(out, k, _time_high(MAX_RAW))
                k = _put(out, k, _time_high(0))
                high = top + 1
            if target != high:
                k = _put(out, k, _time_high(target & MAX_RAW))
            high = target
        elif target < high:
            if (target >> HIGH_BITS) != (high >> HIGH_BITS) or high - target > MAX_BACK_STEPS:
                err[0] = 2 if is_trigger else 1
                err[1] = j if is_trigger else i
                return -1
            k = _put(out, k, _time_high(target & MAX_RAW))
            high = target
        if is_trigger:
            k = _put(out, k, (np.int64(T_EXT_TRIGGER) << 28) | ((now & 63) << 22) | (np.int64(tid[j]) << 8) | np.int64(tp[j]))
            j += 1
        else:
            k = _put(out, k, (np.int64(p[i]) << 28) | ((now & 63) << 22) | (np.int64(x[i]) << 11) | np.int64(y[i]))
            i += 1
    return k
