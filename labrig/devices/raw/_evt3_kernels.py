"""EVT 3.0 word loops (numba): decode 16-bit words into events, encode events into words.

Decoding follows the semantics of Prophesee's standalone EVT3 decoder (events.md section 1):
words before the first TIME_HIGH are skipped; a TIME_HIGH sets the time to its base (low part
0) and counts a 24-bit loop when it drops by at least 4085 steps; TIME_LOW sets base + low, even
backwards; ADDR_X, VECT_12 and VECT_8 are decoded word by word (VECT_BASE_X sets base and
polarity, each vector word advances the base by 12 or 8); EM_Y switches off CD output until
the next ADDR_Y. labrig additions: events outside the geometry are dropped (and logged),
OTHERS/CONTINUED groups are consumed, unknown types and stray CONTINUED words are logged.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from labrig.devices.raw import _state as S

WORD_BYTES = 2
#: Time-high loop in us (2^24), the largest base, and the drop that counts as a loop.
LOOP_US = 1 << 24
MAX_BASE_US = 4095 << 12
LOOP_THRESHOLD_US = 10 << 12
#: Steps of TIME_HIGH that an encoder may go back without the decoder taking it for a loop.
MAX_BACK_STEPS = 4095 - 10 - 1

T_ADDR_Y, T_EM_Y, T_ADDR_X, T_VECT_BASE_X, T_VECT_12, T_VECT_8, T_TIME_LOW = 0x0, 0x1, 0x2, 0x3, 0x4, 0x5, 0x6
T_CONTINUED_4, T_TIME_HIGH, T_EXT_TRIGGER, T_OTHERS, T_CONTINUED_12 = 0x7, 0x8, 0xA, 0xE, 0xF

#: Bit index of a power of two b < 2^32: _DEBRUIJN[(b * 0x077CB531 >> 27) & 31] (de Bruijn sequence).
_DEBRUIJN = np.zeros(32, np.int64)
for _bit in range(32):
    _DEBRUIJN[(((1 << _bit) * 0x077CB531) >> 27) & 31] = _bit


@njit(cache=True, nogil=True)
def decode(words, pos, state, width, height, ev, n_ev, tr, n_tr, runs):
    """Decode ``words[pos:]`` into ``ev[n_ev:]`` / ``tr[n_tr:]``; stop early when either is (nearly) full.

    Returns (next word index, events filled, triggers filled); the state is updated in place.
    """
    n = words.shape[0]
    cap_ev = ev.shape[0] - 12
    cap_tr = tr.shape[0]
    base = state[S.BASE]
    loops = state[S.LOOPS]
    time = state[S.TIME]
    y = state[S.Y]
    y_ok = y < height
    xbase = state[S.XBASE]
    pol = state[S.POL]
    cd = state[S.CD] != 0
    group = state[S.GROUP] != 0
    off0 = state[S.WORD_OFF]
    dropped = 0
    others = 0
    i = pos
    while i < n and state[S.STARTED] == 0:
        w = np.int64(words[i])
        if (w >> 12) == T_TIME_HIGH:
            state[S.STARTED] = 1
            base = (w & 0xFFF) << 12
            time = base
        else:
            S.skip(state, runs, off0 + i * WORD_BYTES, S.BEFORE_TIME_HIGH, WORD_BYTES)
        i += 1
    while i < n:
        w = np.int64(words[i])
        typ = w >> 12
        if typ == T_ADDR_X:
            if cd:
                if n_ev > cap_ev:
                    break
                x = w & 0x7FF
                if x < width and y_ok:
                    e = ev[n_ev]
                    e.x = x
                    e.y = y
                    e.p = (w >> 11) & 1
                    e.t = time
                    n_ev += 1
                else:
                    dropped += 1
                    S.skip(state, runs, off0 + i * WORD_BYTES, S.OUT_OF_GEOMETRY, WORD_BYTES)
        elif typ == T_ADDR_Y:
            y = w & 0x7FF
            y_ok = y < height
            cd = True
        elif typ == T_TIME_LOW:
            time = base + (w & 0xFFF)
        elif typ == T_VECT_12 or typ == T_VECT_8:  # noqa: SIM109 - plain compares in the numba loop
            nbits = 12 if typ == T_VECT_12 else 8
            if cd:
                if n_ev > cap_ev:
                    break
                valid = w & (0xFFF if typ == T_VECT_12 else 0xFF)
                if xbase + nbits <= width and y_ok:
                    while valid:  # one pass per set bit, lowest first
                        low = valid & -valid
                        valid ^= low
                        e = ev[n_ev]
                        e.x = xbase + _DEBRUIJN[((low * 0x077CB531) >> 27) & 31]
                        e.y = y
                        e.p = pol
                        e.t = time
                        n_ev += 1
                else:
                    bad = 0
                    k = 0
                    while valid:
                        if valid & 1:
                            x = xbase + k
                            if x < width and y_ok:
                                e = ev[n_ev]
                                e.x = x
                                e.y = y
                                e.p = pol
                                e.t = time
                                n_ev += 1
                            else:
                                bad += 1
                        valid >>= 1
                        k += 1
                    if bad:
                        dropped += bad
                        S.skip(state, runs, off0 + i * WORD_BYTES, S.OUT_OF_GEOMETRY, WORD_BYTES)
            xbase += nbits
        elif typ == T_VECT_BASE_X:
            xbase = w & 0x7FF
            pol = (w >> 11) & 1
        elif typ == T_TIME_HIGH:
            new_base = ((w & 0xFFF) << 12) + loops * LOOP_US
            if base > new_base and base - new_base >= MAX_BASE_US - LOOP_THRESHOLD_US:
                new_base += LOOP_US
                loops += 1
            base = new_base
            time = base
        elif typ == T_EXT_TRIGGER:
            if n_tr >= cap_tr:
                break
            r = tr[n_tr]
            r.p = w & 1
            r.id = (w >> 8) & 0xF
            r.t = time
            n_tr += 1
        elif typ == T_OTHERS:
            others += 1
            group = True
            i += 1
            continue  # the group stays open for CONTINUED words
        elif typ == T_CONTINUED_12 or typ == T_CONTINUED_4:  # noqa: SIM109
            if group:
                others += 1
                i += 1
                continue
            S.skip(state, runs, off0 + i * WORD_BYTES, S.ORPHAN_CONTINUED, WORD_BYTES)
        elif typ == T_EM_Y:
            cd = False
        else:
            S.skip(state, runs, off0 + i * WORD_BYTES, S.UNKNOWN_TYPE, WORD_BYTES)
        group = False  # any other word ends an OTHERS group
        i += 1
    state[S.BASE] = base
    state[S.LOOPS] = loops
    state[S.TIME] = time
    state[S.Y] = y
    state[S.XBASE] = xbase
    state[S.POL] = pol
    state[S.CD] = 1 if cd else 0
    state[S.GROUP] = 1 if group else 0
    state[S.DROPPED] += dropped
    state[S.OTHERS] += others
    return i, n_ev, n_tr


@njit(cache=True, nogil=True)
def count_events(words):
    """The most CD events ``words`` can decode to: one per ADDR_X, one per set bit of a vector (events that
    :func:`decode` drops, before the first TIME_HIGH, after EM_Y or outside the geometry, are counted)."""
    n = 0
    for i in range(words.shape[0]):
        w = np.int64(words[i])
        typ = w >> 12
        if typ == T_ADDR_X:
            n += 1
        elif typ == T_VECT_12 or typ == T_VECT_8:  # noqa: SIM109 - plain compares in the numba loop
            v = w & (0xFFF if typ == T_VECT_12 else 0xFF)
            while v:
                v &= v - 1
                n += 1
    return n


@njit(cache=True, nogil=True)
def _put(out, k, word):
    if k < out.shape[0]:
        out[k] = word
    return k + 1


@njit(cache=True, nogil=True)
def encode(x, y, p, t, tp, tt, tid, width, time_high_every, vect_min, out, err):
    """Encode events (x, y, p, t) and triggers (tp, tt, tid) into EVT3 words in ``out``.

    Items are taken in input order, a trigger before the next event when its time is earlier.
    Returns the number of words the stream needs (more than ``out`` holds: call again with a
    bigger ``out``). On a time that cannot be written, returns -1 with err = (code, index):
    code 1 = event, 2 = trigger time goes back across a 24-bit loop or by >= 4085 TIME_HIGH steps.
    """
    n = x.shape[0]
    m = tt.shape[0]
    k = 0
    high = np.int64(-1)  # absolute TIME_HIGH the decoder holds (-1: none yet)
    dec_time = np.int64(-1)  # time the decoder holds (-1: unknown, a TIME_LOW is due)
    cur_y = np.int64(-1)
    since_high = 0
    i = 0
    j = 0
    while i < n or j < m:
        is_trigger = j < m and (i >= n or tt[j] < t[i])
        now = np.int64(tt[j]) if is_trigger else np.int64(t[i])
        target = now >> 12
        if high < 0:
            if target >= 4096:  # climb from 0 through whole loops so the absolute time survives
                k = _put(out, k, (T_TIME_HIGH << 12) | 0)
                high = 0
                while (target >> 12) > (high >> 12):
                    k = _put(out, k, (T_TIME_HIGH << 12) | 0xFFF)
                    k = _put(out, k, (T_TIME_HIGH << 12) | 0)
                    high = ((high >> 12) + 1) << 12
            elif (target & 0xFF) == 0x25:  # first byte '%' would read as a header line
                k = _put(out, k, (T_TIME_HIGH << 12) | (target - 1))
            k = _put(out, k, (T_TIME_HIGH << 12) | (target & 0xFFF))
            high = target
            dec_time = -1
            since_high = 0
        elif target != high or since_high >= time_high_every:
            if target > high:
                h = high + 1
                while h <= target:  # every step, as the sensor does; 4095 -> 0 marks a loop
                    k = _put(out, k, (T_TIME_HIGH << 12) | (h & 0xFFF))
                    h += 1
            else:
                if (target >> 12) != (high >> 12) or high - target > MAX_BACK_STEPS:
                    err[0] = 2 if is_trigger else 1
                    err[1] = j if is_trigger else i
                    return -1
                k = _put(out, k, (T_TIME_HIGH << 12) | (target & 0xFFF))
            high = target
            dec_time = -1
            since_high = 0
        if dec_time != now:
            k = _put(out, k, (T_TIME_LOW << 12) | (now & 0xFFF))
            dec_time = now
            since_high += 1
        if is_trigger:
            k = _put(out, k, (T_EXT_TRIGGER << 12) | (np.int64(tid[j]) << 8) | np.int64(tp[j]))
            since_high += 1
            j += 1
            continue
        yi = np.int64(y[i])
        pi = np.int64(p[i])
        xi = np.int64(x[i])
        if yi != cur_y:
            k = _put(out, k, (T_ADDR_Y << 12) | yi)
            cur_y = yi
            since_high += 1
        b = xi & ~np.int64(31)
        if vect_min > 0 and b + 32 <= width:
            mask = np.int64(1) << (xi - b)
            last = xi
            jj = i + 1
            while jj < n and np.int64(t[jj]) == now and np.int64(y[jj]) == yi and np.int64(p[jj]) == pi:
                xj = np.int64(x[jj])
                if xj <= last or xj >= b + 32:
                    break
                mask |= np.int64(1) << (xj - b)
                last = xj
                jj += 1
            if jj - i >= vect_min:
                k = _put(out, k, (T_VECT_BASE_X << 12) | (pi << 11) | b)
                k = _put(out, k, (T_VECT_12 << 12) | (mask & 0xFFF))
                k = _put(out, k, (T_VECT_12 << 12) | ((mask >> 12) & 0xFFF))
                k = _put(out, k, (T_VECT_8 << 12) | ((mask >> 24) & 0xFF))
                since_high += 4
                i = jj
                continue
        k = _put(out, k, (T_ADDR_X << 12) | (pi << 11) | xi)
        since_high += 1
        i += 1
    return k
