"""Fused per-pixel loops (numba) for the dense passes of the virtual rig's camera.

When the membrane's shading changes, most of the ROI (~450k pixels) is
re-shaded, composed, compared with the reported image and fed to the event
sensor. In numpy each of those steps is a pass over the rectangle with its own
temporaries; here each side (renderer, sensor) is one loop. The arithmetic is
the numpy code's, operation for operation (no fastmath), so results do not
depend on which path computed them.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _bilinear(nodes, nx, b, t, u):  # type: ignore[no-untyped-def]
    """The node values' bilinear blend at lower-left node ``b`` (flat, ``nx`` per row), offsets ``t``, ``u``
    (as :meth:`~labrig.sim.shading.GridLookup.sample`, operation for operation)."""
    low = nodes[b]
    low += (nodes[b + 1] - low) * t
    high = nodes[b + nx]
    high += (nodes[b + nx + 1] - high) * t
    high -= low
    high *= u
    low += high
    return low


@njit(cache=True, nogil=True)
def shade_compose(
    rect, shade_rect, nodes, nx, base, tx, ty, grid, gel_x, gel_y, gain, shade, lum, pad, reported, led, rel, changed,
    values
):  # type: ignore[no-untyped-def]
    """Re-shade ``shade_rect`` and compose ``rect`` (both x0, x1, y0, y1 in ROI pixels); return the changed count.

    Shading (ROI, in place): ``1 + gain * slope`` inside ``shade_rect`` (may be
    empty), the slope interpolated bilinearly from ``nodes`` (flat node slopes,
    ``nx`` per row, followed by at least nx + 2 zeros). The weights come from a
    table when ``base`` is ROI-shaped: each pixel's lower-left node ``base``
    (pixels off the grid point into the zeros) and fractional offsets ``tx``,
    ``ty`` (as :meth:`~labrig.sim.shading.GridLookup.sample`); otherwise they are
    computed here from each pixel's rest gel point (``gel_x``, ``gel_y``, mm,
    ROI-shaped) on ``grid`` = (x0, x1, nx, y0, y1, ny) (mm, nodes), as
    :meth:`~labrig.sim.shading.GridLookup.build` would (a sliding contact's grid
    moves at every render, and a table for every ROI pixel would be rebuilt each time).
    Composition over ``rect``: ``led * min(shade * lum, 1)`` (``led`` the LED ring's level, 1 full,
    0 off; ``lum`` is the canvas, the ROI at offset ``pad``); a pixel whose intensity
    moved by more than ``rel * (old + new + 1e-3)`` is updated in ``reported``
    and marked in ``changed`` (rect-shaped); ``values`` (rect-shaped) receives
    ``reported`` after the update.
    """
    x0, x1, y0, y1 = rect
    sx0, sx1, sy0, sy1 = shade_rect
    tabulated = base.shape[0] == shade.shape[0] and base.shape[1] == shade.shape[1]
    gx0, gx1, _, gy0, gy1, fny = grid
    ny = int(fny)
    count = 0
    for i in range(y0, y1):
        if sy0 <= i < sy1 and sx1 > sx0 and tabulated:
            b_row, tx_row, ty_row, s_row = base[i, sx0:sx1], tx[i, sx0:sx1], ty[i, sx0:sx1], shade[i, sx0:sx1]
            for j in range(sx1 - sx0):
                s_row[j] = 1.0 + gain * _bilinear(nodes, nx, b_row[j], tx_row[j], ty_row[j])
        elif sy0 <= i < sy1 and sx1 > sx0:
            px_row, py_row, s_row = gel_x[i, sx0:sx1], gel_y[i, sx0:sx1], shade[i, sx0:sx1]
            for j in range(sx1 - sx0):
                fx = (px_row[j] - gx0) / (gx1 - gx0) * (nx - 1)
                fy = (py_row[j] - gy0) / (gy1 - gy0) * (ny - 1)
                if not (fx >= 0 and fx <= nx - 1 and fy >= 0 and fy <= ny - 1):
                    s_row[j] = 1.0
                    continue
                ix = min(max(int(np.floor(fx)), 0), nx - 2)
                iy = min(max(int(np.floor(fy)), 0), ny - 2)
                t = min(max(fx - ix, 0.0), 1.0)
                u = min(max(fy - iy, 0.0), 1.0)
                s_row[j] = 1.0 + gain * _bilinear(nodes, nx, iy * nx + ix, t, u)
        s_row, l_row, r_row = shade[i, x0:x1], lum[i + pad, x0 + pad : x1 + pad], reported[i, x0:x1]
        c_row, v_row = changed[i - y0], values[i - y0]
        for j in range(x1 - x0):
            new = min(s_row[j] * l_row[j], 1.0) * led
            old = r_row[j]
            limit = old + new
            limit += 1e-3
            limit *= rel
            moved = abs(new - old) > limit
            v = new if moved else old
            r_row[j] = v
            v_row[j] = v
            c_row[j] = moved
            count += moved
    return count


@njit(cache=True, nogil=True, inline="always")
def outside_band(y, hi, lo, k, to_end, to_start):  # type: ignore[no-untyped-def]
    """Whether a pixel's filtered log intensity ``y`` may cross a threshold within the leak epoch.

    The band is kept free of time: ``hi = R + C_on - margin`` and ``lo = R - C_off + margin``
    change only when the reference R does. With D = Lf - R + k (t - t_start) growing by the
    leak ``k`` (ln units per us), an ON crossing (or a leak) by the epoch's end needs
    ``y + k to_end >= hi`` and an OFF crossing after its start ``y + k to_start <= lo``
    (``to_end``, ``to_start``: the epoch's ends minus ``t_start``, us).
    """
    return y + k * to_end >= hi or y + k * to_start <= lo


@njit(cache=True, nogil=True)
def sensor_block(
    y0, x0, width, changed, values, eps, log_input, log_filtered, hi, lo, k, to_end, to_start, is_active, a, b, c, settle,
    who, before, after, active
):  # type: ignore[no-untyped-def]
    """Low-pass update of a dense block's changed pixels and of the unsettled pixels in it.

    The block is rows y0.., columns x0.. of a window ``width`` wide; ``changed``
    and ``values`` (linear intensity) are block-shaped, the state (``log_input``,
    ``log_filtered``, the no-crossing band ``hi``/``lo``, ``is_active``) flat
    over the window. A changed pixel's new log input is ``log(eps + value)``; an
    unchanged one keeps its stored log input (its value is the one that gave it).
    Updated pixels get ``y1 = a y0 + b u1 + c u0`` (u: log input before and
    after). Writes, in row-major order, the updated pixels whose ``y1`` left the
    epoch's band (:func:`outside_band`: ``k``, ``to_end``, ``to_start``) (``who``,
    ``before``, ``after``) and those left unsettled
    (|u1 - y1| > settle: ``active``); returns both counts.
    """
    h, w = changed.shape
    n_who = 0
    n_active = 0
    for r in range(h):
        start = (r + y0) * width + x0
        c_row, value_row = changed[r], values[r]
        u_row, y_row = log_input[start : start + w], log_filtered[start : start + w]
        hi_row, lo_row, a_row = hi[start : start + w], lo[start : start + w], is_active[start : start + w]
        k_row = k[start : start + w]
        for col in range(w):
            if c_row[col]:
                u1 = np.log(eps + value_row[col])
            elif a_row[col]:
                u1 = u_row[col]
            else:
                continue
            y_0 = y_row[col]
            y1 = a * y_0
            y1 += b * u1
            y1 += c * u_row[col]
            if outside_band(y1, hi_row[col], lo_row[col], k_row[col], to_end, to_start):
                who[n_who] = start + col
                before[n_who] = y_0
                after[n_who] = y1
                n_who += 1
            if abs(u1 - y1) > settle:
                active[n_active] = start + col
                n_active += 1
            y_row[col] = y1
            u_row[col] = u1
    return n_who, n_active


@njit(cache=True, nogil=True)
def sensor_list(
    pixels, log_new, old_active, rect, width, mark, stamp, log_input, log_filtered, hi, lo, k_all, to_end, to_start,
    a, b, c, settle, who, before, after, active,
):  # type: ignore[no-untyped-def]
    """Low-pass update of scattered pixels (new log input ``log_new``) and of the still unsettled ones.

    ``old_active`` pixels count only if not among ``pixels`` (``mark`` is set to
    ``stamp`` for those) nor inside ``rect`` (y0, y1, x0, x1 of a dense block
    updated already). Outputs as :func:`sensor_block`, in the order ``pixels``
    then ``old_active``; returns both counts.
    """
    n_who = 0
    n_active = 0
    ry0, ry1, rx0, rx1 = rect
    total = pixels.size + old_active.size
    for i in range(total):
        if i < pixels.size:
            k = pixels[i]
            mark[k] = stamp
            u0 = log_input[k]
            u1 = log_new[i]
        else:
            k = old_active[i - pixels.size]
            if mark[k] == stamp:
                continue
            y, x = k // width, k % width
            if ry0 <= y < ry1 and rx0 <= x < rx1:
                continue
            u0 = log_input[k]
            u1 = u0
        y_0 = log_filtered[k]
        y1 = a * y_0
        y1 += b * u1
        y1 += c * u0
        if outside_band(y1, hi[k], lo[k], k_all[k], to_end, to_start):
            who[n_who] = k
            before[n_who] = y_0
            after[n_who] = y1
            n_who += 1
        if abs(u1 - y1) > settle:
            active[n_active] = k
            n_active += 1
        log_filtered[k] = y1
        log_input[k] = u1
    return n_who, n_active


@njit(cache=True, nogil=True, error_model="numpy")
def rim_change(
    markers, centres, o1, o0, qa, qb, qc, low, high, span0, span1, edge, patches, corner, cw, cov, out_pix, out_delta
):  # type: ignore[no-untyped-def]
    """Coverage change of markers moved within their rims (see Renderer._move_markers); return its count.

    For each moved marker k (index ``markers[k]`` into the stored full
    patches, side S): the patch is re-expressed at its new origin ``o1[k]``
    (from ``o0[k]``; pixels entering it are empty); the candidate pixels
    (patch rows and columns ``span0 <= . < span1`` whose offset from the new
    centre lies between ``low[k]`` and ``high[k]`` px) get the new coverage
    (as :func:`labrig.sim.discs.coverage_at`, for Q = [[qa, qb], [qb, qc]]);
    where it differs from the stored value, the difference is added to the
    canvas coverage ``cov`` at ``corner[k] + row * cw + col`` and written to
    ``out_pix`` / ``out_delta`` (marker by marker, rows then columns).
    """
    side = patches.shape[1]
    tmp = np.empty((side, side))
    n = 0
    for k in range(markers.size):
        patch = patches[markers[k]]
        dx = o1[k, 0] - o0[k, 0]
        dy = o1[k, 1] - o0[k, 1]
        if dx != 0 or dy != 0:
            tmp[:, :] = patch
            for r in range(side):
                for col in range(side):
                    rr, cc = r + dy, col + dx
                    patch[r, col] = tmp[rr, cc] if 0 <= rr < side and 0 <= cc < side else 0.0
        ox = o1[k, 0] - centres[k, 0]
        oy = o1[k, 1] - centres[k, 1]
        lo2 = low[k] * low[k]
        hi2 = high[k] * high[k]
        a, b, c = qa[k], qb[k], qc[k]
        for row in range(span0, span1):
            qy = oy + row
            for col in range(span0, span1):
                qx = ox + col
                r2 = qx * qx
                r2 += qy * qy
                if r2 < lo2 or r2 > hi2:
                    continue
                gx = a * qx + b * qy
                gy = b * qx + c * qy
                f = qx * gx
                f += qy * gy
                f = np.sqrt(f)
                grad = np.sqrt(gx * gx + gy * gy)
                d = f - 1.0
                d *= f
                d /= grad
                if edge != 1.0:
                    d /= edge
                new = 0.5 - d
                if not new <= 1.0:  # above 1, or NaN at the centre (0/0): full coverage, as np.fmin
                    new = 1.0
                elif new < 0.0:
                    new = 0.0
                delta = new - patch[row, col]
                patch[row, col] = new
                if delta != 0.0:
                    pix = corner[k] + row * cw + col
                    cov[pix] += delta
                    out_pix[n] = pix
                    out_delta[n] = delta
                    n += 1
    return n


@njit(cache=True, nogil=True)
def moved_markers(centres, axes, old_centres, old_axes, min_move):  # type: ignore[no-untyped-def]
    """Indices of the markers whose image centre (K, 2) or axes (K, 2, 2) moved by more than ``min_move`` px
    (the largest absolute change of any coordinate), increasing."""
    out = np.empty(centres.shape[0], np.int64)
    n = 0
    for k in range(centres.shape[0]):
        shift = max(abs(centres[k, 0] - old_centres[k, 0]), abs(centres[k, 1] - old_centres[k, 1]))
        for i in range(2):
            for j in range(2):
                shift = max(shift, abs(axes[k, i, j] - old_axes[k, i, j]))
        if shift > min_move:
            out[n] = k
            n += 1
    return out[:n]


@njit(cache=True, nogil=True, error_model="numpy")
def rim_moves(
    moved, c1, aat, half, edge, inked, centres, axes_new, axes, origins, inner, outer, patches, pad, roi_x0, roi_y0,
    ch, cw, cov,
):  # type: ignore[no-untyped-def]
    """Renderer._move_markers for the moved markers that stay within their rims, in one call.

    ``moved`` (M,): the markers; ``c1`` (M, 2) their new centres; ``aat`` (M, 2, 2) A A^T of their new axes
    (numpy's product, as :func:`labrig.sim.discs.rim_radii` and :func:`~labrig.sim.discs.inverse_shape` take
    it). Per marker, as those and :func:`labrig.sim.discs.patch_origins`: the new rim radii, the candidate
    annulus (the old rims widened by the move, 0.05 px margins), the new patch origin; a marker whose annulus
    stays inside its patch (and every marker only when not ``inked``) takes :func:`rim_change` (its coverage
    change added to ``cov``) and its stored state (``centres``, ``axes`` from ``axes_new``, ``origins``,
    ``inner``, ``outer``) is updated. Returns the changed canvas pixels and whether each moved marker took
    that path (the others are left to the caller, state untouched); also their new origins and radii.
    """
    m = moved.size
    inner1, outer1, low, high = np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    o1 = np.empty((m, 2), np.int64)
    rim = np.zeros(m, np.bool_)
    n_rim = 0
    high_max = -np.inf
    for i in range(m):
        k = moved[i]
        a00, a01, a11 = aat[i, 0, 0], aat[i, 0, 1], aat[i, 1, 1]
        mean = (a00 + a11) / 2
        half_diff = (a00 - a11) / 2
        spread = np.sqrt(half_diff * half_diff + a01 * a01)
        s1 = np.sqrt(mean + spread)
        s2 = np.sqrt(max(mean - spread, 1e-300))
        ratio = s1 / s2
        inner1[i] = s2 - edge / 2 * s1 / s2
        outer1[i] = s1 + edge / 2 * (ratio * ratio)
        move = np.hypot(c1[i, 0] - centres[k, 0], c1[i, 1] - centres[k, 1])
        low[i] = max(min(inner[k] - move, inner1[i]) - 0.05, 0.0)
        high[i] = max(outer[k] + move, outer1[i]) + 0.05
        o1[i, 0] = np.int64(np.floor(c1[i, 0])) - half + 1
        o1[i, 1] = np.int64(np.floor(c1[i, 1])) - half + 1
        if not inked and high[i] <= half - 1:
            rim[i] = True
            n_rim += 1
            high_max = max(high_max, high[i])
    if n_rim == 0:
        return np.empty(0, np.int64), rim, o1, inner1, outer1
    side = 2 * half
    reach = min(int(np.ceil(high_max)), half - 1)
    span0, span1 = half - 1 - reach, half + reach + 1
    markers = np.empty(n_rim, np.int64)
    rc1, ro1, ro0 = np.empty((n_rim, 2)), np.empty((n_rim, 2), np.int64), np.empty((n_rim, 2), np.int64)
    qa, qb, qc = np.empty(n_rim), np.empty(n_rim), np.empty(n_rim)
    rlow, rhigh, corner = np.empty(n_rim), np.empty(n_rim), np.empty(n_rim, np.int64)
    j = 0
    for i in range(m):
        if not rim[i]:
            continue
        k = moved[i]
        markers[j] = k
        rc1[j, 0], rc1[j, 1] = c1[i, 0], c1[i, 1]
        ro1[j, 0], ro1[j, 1] = o1[i, 0], o1[i, 1]
        ro0[j, 0], ro0[j, 1] = origins[k, 0], origins[k, 1]
        a00, a01, a11 = aat[i, 0, 0], aat[i, 0, 1], aat[i, 1, 1]
        det = a00 * a11 - a01 * a01
        qa[j], qb[j], qc[j] = a11 / det, -a01 / det, a00 / det
        rlow[j], rhigh[j] = low[i], high[i]
        ox = min(max(o1[i, 0] - roi_x0 + pad, 0), cw - side)
        oy = min(max(o1[i, 1] - roi_y0 + pad, 0), ch - side)
        corner[j] = oy * cw + ox
        j += 1
    size = n_rim * (span1 - span0) ** 2
    pixels, delta = np.empty(size, np.int64), np.empty(size)
    n = rim_change(markers, rc1, ro1, ro0, qa, qb, qc, rlow, rhigh, span0, span1, edge, patches, corner, cw, cov,
                   pixels, delta)
    for i in range(m):
        if rim[i]:
            k = moved[i]
            centres[k, 0], centres[k, 1] = c1[i, 0], c1[i, 1]
            axes[k] = axes_new[i]
            origins[k, 0], origins[k, 1] = o1[i, 0], o1[i, 1]
            inner[k], outer[k] = inner1[i], outer1[i]
    return pixels[:n], rim, o1, inner1, outer1


@njit(cache=True, nogil=True)
def touch_luminance(pixels, scratch, cov, membrane, marker, cov_max, lum, canvas_to_roi, block, width, out):
    """The distinct canvas pixels of ``pixels`` get their luminance ``membrane + clip(cov, 0, cov_max) *
    (marker - membrane)`` (as Renderer._luminance); returns how many of them are ROI pixels outside
    ``block`` (x0, x1, y0, y1, ROI pixels; empty: x1 <= x0), written as flat ROI indices to ``out``.

    Each distinct value is kept at its last occurrence, in list order (overlapping markers repeat
    pixels); ``scratch`` (int64, longer than the largest index) is overwritten.
    """
    for i in range(pixels.size):
        scratch[pixels[i]] = i
    bx0, bx1, by0, by1 = block
    span = marker - membrane
    n = 0
    for i in range(pixels.size):
        p = pixels[i]
        if scratch[p] != i:
            continue
        c = min(max(cov[p], 0.0), cov_max)
        lum[p] = membrane + c * span
        roi = canvas_to_roi[p]
        if roi < 0:
            continue
        if bx1 > bx0:
            y = roi // width
            x = roi - y * width
            if by0 <= y < by1 and bx0 <= x < bx1:
                continue
        out[n] = roi
        n += 1
    return n


@njit(cache=True, nogil=True)
def compose_list(pixels, n, roi_to_canvas, lum, shade, reported, led, rel, out_pix, out_val):
    """Compose ROI pixels ``pixels[:n]`` (``led * min(shade * lum, 1)``, ``led`` the LED ring's level) and keep those whose
    intensity moved by more than ``rel * (old + new + 1e-3)`` (as :func:`shade_compose`): ``reported`` is
    updated there and they are written, in order, to ``out_pix`` / ``out_val``; returns their count."""
    m = 0
    for i in range(n):
        k = pixels[i]
        new = min(shade[k] * lum[roi_to_canvas[k]], 1.0) * led
        old = reported[k]
        limit = old + new
        limit += 1e-3
        limit *= rel
        if abs(new - old) > limit:
            reported[k] = new
            out_pix[m] = k
            out_val[m] = new
            m += 1
    return m


@njit(cache=True, nogil=True)
def crossings(
    t0, t1, who, y0, y1, reference, c_on_all, c_off_all, k_all, leak, t_start, to_end, hi, lo,
    last_event, refractory, out_pix, out_pol, out_t, leak_candidates,
):  # type: ignore[no-untyped-def]
    """Threshold crossings of pixels ``who`` whose filtered log intensity went y0 -> y1 over [t0, t1] us.

    The arithmetic of EventSensor's model (module docstring of labrig.sim.events),
    per pixel: D = Lf - R + k (t - t_start); a pixel whose D ends at or beyond
    C_on (or -C_off) moves its reference by the whole crossings, gets a fresh
    no-crossing band (``hi``, ``lo``, see :func:`outside_band`) and emits the crossings its
    refractory period keeps (times linear in the step, floored to us, clipped
    to the step), updating ``last_event``. Events are written pixel by pixel
    (``out_*``, room for every crossing); with ``leak``, the pixels that may
    leak before the epoch's end (``to_end``: its end minus ``t_start``, us) are
    written to ``leak_candidates``. Returns (events, leak candidates).
    """
    dt = t1 - t0
    n = 0
    for i in range(who.size):
        p = who[i]
        c_on = c_on_all[p]
        c_off = c_off_all[p]
        offset = -reference[p]
        if leak:
            kk = k_all[p]
            offset += kk * (t0 - t_start)
            d0 = y0[i] + offset
            d1 = y1[i] + offset + kk * dt
        else:
            d0 = y0[i] + offset
            d1 = y1[i] + offset
        if not (d1 >= c_on or d1 <= -c_off):
            continue
        rising = d1 > d0
        c = c_on if rising else c_off
        count = np.floor(abs(d1) / c)
        reference[p] += (count if rising else -count) * c
        r = reference[p]
        kk = k_all[p]
        hi[p] = r + c_on - 1e-9
        lo[p] = r - c_off + 1e-9
        step = max(abs(d1 - d0), 1e-12)
        first = c_on - d0 if rising else d0 + c_off
        t_first = t0 + first / step * dt
        spacing = c / step * dt
        if refractory == 0:
            j0, every = 0, 1
        else:
            allowed = float(last_event[p] + refractory)
            j0f = max(np.ceil((allowed - t_first) / spacing), 0.0)
            if t_first + j0f * spacing < allowed:
                j0f += 1.0
            everyf = max(np.ceil(refractory / spacing), 1.0)
            if everyf * spacing < refractory:
                everyf += 1.0
            j0, every = int(min(j0f, 2.0**40)), int(min(everyf, 2.0**40))
        count_i = int(count)
        kept = (count_i - 1 - j0) // every + 1 if j0 < count_i else 0
        for e in range(kept):
            t = t_first + (j0 + e * every) * spacing
            ti = min(max(int(np.floor(t + 1e-6)), t0), t1)
            out_pix[n] = p
            out_pol[n] = 1 if rising else 0
            out_t[n] = ti
            last_event[p] = ti
            n += 1
    m = 0
    if leak:
        for i in range(who.size):
            if y1[i] + k_all[who[i]] * to_end >= hi[who[i]]:
                leak_candidates[m] = who[i]
                m += 1
    return n, m


@njit(cache=True, nogil=True)
def epoch_leak_candidates(k, to_end, log_filtered, hi, candidates):  # type: ignore[no-untyped-def]
    """The pixels that may leak before a new leak epoch's end, in increasing order, into ``candidates``:
    ``Lf + k to_end >= hi`` (:func:`outside_band`'s ON side; ``to_end``: the epoch's end minus
    ``t_start``, us). Returns how many."""
    m = 0
    for i in range(k.size):
        if log_filtered[i] + k[i] * to_end >= hi[i]:
            candidates[m] = i
            m += 1
    return m


@njit(cache=True, nogil=True)
def leak_due(cand, t_start, t1, c_on_all, k_all, reference, log_filtered, hi, to_end, is_candidate, out_due,
             out_kept):  # type: ignore[no-untyped-def]
    """The candidates whose next leak time is at or before ``t1`` (as :func:`quiet_leak` finds it), into
    ``out_due``; those still at or above their band's top (the only ones that may leak before the
    epoch's end, :func:`epoch_leak_candidates`) into ``out_kept``, the others leave the candidates
    (``is_candidate``). Returns both counts."""
    m = 0
    kept = 0
    for i in range(cand.size):
        p = cand[i]
        if t_start + (c_on_all[p] + reference[p] - log_filtered[p]) / k_all[p] <= t1:
            out_due[m] = p
            m += 1
        if log_filtered[p] + k_all[p] * to_end >= hi[p]:
            out_kept[kept] = p
            kept += 1
        else:
            is_candidate[p] = False
    return m, kept


@njit(cache=True, nogil=True)
def quiet_leak(cand, t_start, t1, c_on_all, c_off_all, k_all, reference, log_filtered, last_event, refractory,
               hi, lo, count_only, out_pix, out_t):  # type: ignore[no-untyped-def]
    """Leak events due by ``t1`` of the quiet candidate pixels ``cand`` (the leak of labrig.sim.events' model).

    A pixel leaks at ``t_start + (C_on + R - Lf) / k``; each leak moves R by C_on and
    refreshes its band (:func:`outside_band`); one that its refractory period keeps is written
    (``out_pix``, ``out_t``) and updates ``last_event``. ``count_only``: change nothing,
    return how many leaks are due (the room the writing pass needs). Returns the count
    of leaks (``count_only``) or of events written.
    """
    n = 0
    for i in range(cand.size):
        p = cand[i]
        c_on = c_on_all[p]
        kk = k_all[p]
        r = reference[p]
        lf = log_filtered[p]
        last = last_event[p]
        while True:
            t = t_start + (c_on + r - lf) / kk
            if not t <= t1:
                break
            if count_only:
                r += c_on
                n += 1
                continue
            t_int = np.int64(np.floor(t + 1e-6))
            r += c_on
            reference[p] = r
            hi[p] = r + c_on - 1e-9
            lo[p] = r - c_off_all[p] + 1e-9
            if t >= last + refractory:
                last = t_int
                last_event[p] = t_int
                out_pix[n] = p
                out_t[n] = t_int
                n += 1
    return n


@njit(cache=True, nogil=True)
def clear_noise(pix, t, noise_pix, noise_t, noise_last, refractory, mark, keep):  # type: ignore[no-untyped-def]
    """Which shot-noise events keep clear of every other event of their pixel by ``refractory`` (us).

    ``pix``, ``t``: the step's other events (signal, leak); ``noise_pix``, ``noise_t``: the noise
    events, ``noise_last`` their pixels' last event time before the step. A noise event is kept
    (``keep``, bool, one per noise event) when it comes at least ``refractory`` after its pixel's
    last event and at least ``refractory`` away from each other event of its pixel in the step,
    noise included (two noise events too close are both dropped). ``mark`` is scratch over the
    pixels. Returns the number kept.
    """
    n_noise = noise_pix.size
    for i in range(pix.size):
        mark[pix[i]] = 0
    for j in range(n_noise):
        mark[noise_pix[j]] = -1
    near = 0
    for i in range(pix.size):
        if mark[pix[i]] == -1:
            near += 1
    size = near + n_noise
    all_pix = np.empty(size, np.int64)
    all_t = np.empty(size, np.int64)
    noise_at = np.full(size, -1, np.int64)
    k = 0
    for i in range(pix.size):
        if mark[pix[i]] == -1:
            all_pix[k] = pix[i]
            all_t[k] = t[i]
            k += 1
    for j in range(n_noise):
        all_pix[k] = noise_pix[j]
        all_t[k] = noise_t[j]
        noise_at[k] = j
        k += 1
    t_min = all_t.min() if size else 0
    span = (all_t.max() - t_min + 1) if size else 1
    order = np.argsort(all_pix * span + (all_t - t_min), kind="mergesort")
    kept = 0
    for m in range(size):
        j = noise_at[order[m]]
        if j < 0:
            continue
        p, tm = all_pix[order[m]], all_t[order[m]]
        ok = noise_t[j] >= noise_last[j] + refractory
        if ok and m > 0 and all_pix[order[m - 1]] == p and tm - all_t[order[m - 1]] < refractory:
            ok = False
        if ok and m + 1 < size and all_pix[order[m + 1]] == p and all_t[order[m + 1]] - tm < refractory:
            ok = False
        keep[j] = ok
        kept += ok
    return kept


@njit(cache=True, nogil=True)
def translate_nodes(values, dx_nodes, dy_nodes, out):  # type: ignore[no-untyped-def]
    """``out[j, i]``: ``values`` (ny, nx) interpolated bilinearly at node (i + ``dx_nodes``, j + ``dy_nodes``) of its
    own grid (:func:`_bilinear`'s arithmetic), 0 off it: a grid's values seen from the same grid translated."""
    ny, nx = values.shape
    flat = np.zeros(values.size + nx + 2)
    flat[: values.size] = values.ravel()
    for j in range(ny):
        fy = j + dy_nodes
        for i in range(nx):
            fx = i + dx_nodes
            if not (fx >= 0 and fx <= nx - 1 and fy >= 0 and fy <= ny - 1):
                out[j, i] = 0.0
                continue
            ix = min(max(int(np.floor(fx)), 0), nx - 2)
            iy = min(max(int(np.floor(fy)), 0), ny - 2)
            t = min(max(fx - ix, 0.0), 1.0)
            u = min(max(fy - iy, 0.0), 1.0)
            out[j, i] = _bilinear(flat, nx, iy * nx + ix, t, u)


@njit(cache=True, nogil=True)
def slope_magnitude(depth, dx, dy, out):  # type: ignore[no-untyped-def]
    """|grad depth| at the nodes of a (ny, nx) grid into ``out``: central differences, one-sided at the
    edges (as np.gradient; the numpy code's arithmetic, operation for operation)."""
    ny, nx = depth.shape
    for j in range(ny):
        for i in range(nx):
            if i == 0:
                gx = (depth[j, 1] - depth[j, 0]) / dx
            elif i == nx - 1:
                gx = (depth[j, nx - 1] - depth[j, nx - 2]) / dx
            else:
                gx = (depth[j, i + 1] - depth[j, i - 1]) / (2.0 * dx)
            if j == 0:
                gy = (depth[1, i] - depth[0, i]) / dy
            elif j == ny - 1:
                gy = (depth[ny - 1, i] - depth[ny - 2, i]) / dy
            else:
                gy = (depth[j + 1, i] - depth[j - 1, i]) / (2.0 * dy)
            gx *= gx
            gy *= gy
            gx += gy
            out[j, i] = np.sqrt(gx)


@njit(cache=True, nogil=True)
def above_box(values, tol):  # type: ignore[no-untyped-def]
    """(row0, row1, col0, col1), inclusive, of the entries of a 2-D array above ``tol``; row0 = -1 if none."""
    ny, nx = values.shape
    r0, r1, c0, c1 = -1, -1, nx, -1
    for j in range(ny):
        for i in range(nx):
            if values[j, i] > tol:
                if r0 < 0:
                    r0 = j
                r1 = j
                c0 = min(c0, i)
                c1 = max(c1, i)
    return r0, r1, c0, c1


@njit(cache=True, nogil=True)
def sensor_step(
    t0, t1, pixels, log_new, old_active, has_block, block_y0, block_x0, block_changed, block_values, eps, width, mark,
    stamp, log_input, log_filtered, hi, lo, is_active, a, b, c, settle, reference, c_on, c_off, k, leak, t_start,
    epoch_start, epoch_end, last_event, refractory, c_max, c_min, k_max, leak_candidates, is_candidate, noise_pix,
    noise_pol, noise_t, noise_last, scratch, dead, has_dead,
):  # type: ignore[no-untyped-def]
    """One step of EventSensor after its noise draw and epoch start (EventSensor.step's sequence, in one call).

    The dense block (``has_block``) and the scattered pixels with the unsettled ones
    (:func:`sensor_block`, :func:`sensor_list`), the new unsettled set, the crossings
    with their leak candidates, the quiet pixels' leak (:func:`leak_due`,
    :func:`quiet_leak`), the shot noise kept clear of the other events
    (:func:`clear_noise`) and dead pixels dropped. Returns the events (pixels,
    polarities, times, and their sort key by (t, pixel, polarity)), the new
    unsettled set and the new leak candidates; the state arrays are updated in place.
    """
    dt = t1 - t0
    size = log_input.size
    to_end, to_start = epoch_end - t_start, epoch_start - t_start
    # Low-pass updates: the block, then the scattered and unsettled pixels outside it.
    n_block = block_changed.size if has_block else 0
    b_who, b_before, b_after = np.empty(n_block, np.int64), np.empty(n_block), np.empty(n_block)
    b_active = np.empty(n_block, np.int64)
    n_bw, n_ba = 0, 0
    ry0, ry1, rx0, rx1 = 0, 0, 0, 0
    if has_block:
        n_bw, n_ba = sensor_block(block_y0, block_x0, width, block_changed, block_values, eps, log_input, log_filtered,
                                  hi, lo, k, to_end, to_start, is_active, a, b, c, settle, b_who, b_before, b_after,
                                  b_active)
        h, w = block_changed.shape
        ry0, ry1, rx0, rx1 = block_y0, block_y0 + h, block_x0, block_x0 + w
    n_list = pixels.size + old_active.size
    l_who, l_before, l_after = np.empty(n_list, np.int64), np.empty(n_list), np.empty(n_list)
    l_active = np.empty(n_list, np.int64)
    n_lw, n_la = 0, 0
    if n_list:
        n_lw, n_la = sensor_list(pixels, log_new, old_active, (ry0, ry1, rx0, rx1), width, mark, stamp, log_input,
                                 log_filtered, hi, lo, k, to_end, to_start, a, b, c, settle, l_who, l_before, l_after,
                                 l_active)
    for i in range(old_active.size):
        is_active[old_active[i]] = False
    active = np.empty(n_ba + n_la, np.int64)
    active[:n_ba] = b_active[:n_ba]
    active[n_ba:] = l_active[:n_la]
    for i in range(active.size):
        is_active[active[i]] = True
    # Threshold crossings. Room for every event: D starts within about one threshold of 0, so a pixel crosses at
    # most (|y1 - y0| + 2 C_max + k dt) / C_min times, and its refractory period keeps at most dt / r + 2.
    n_who = n_bw + n_lw
    who, y0, y1 = np.empty(n_who, np.int64), np.empty(n_who), np.empty(n_who)
    who[:n_bw], y0[:n_bw], y1[:n_bw] = b_who[:n_bw], b_before[:n_bw], b_after[:n_bw]
    who[n_bw:], y0[n_bw:], y1[n_bw:] = l_who[:n_lw], l_before[:n_lw], l_after[:n_lw]
    room = 2 * n_who
    spread = 2 * c_max + k_max * dt
    bound_sum = 0.0
    for i in range(n_who):
        bound = (abs(y1[i] - y0[i]) + spread) / c_min
        if refractory:
            bound = min(bound, dt // refractory + 2)
        bound_sum += bound
    room += int(bound_sum) + 1
    sig_pix, sig_pol, sig_t = np.empty(room, np.int64), np.empty(room, np.uint8), np.empty(room, np.int64)
    found = np.empty(n_who, np.int64)
    n_sig, n_found = 0, 0
    if n_who:
        n_sig, n_found = crossings(t0, t1, who, y0, y1, reference, c_on, c_off, k, leak, t_start, to_end,
                                   hi, lo, last_event, refractory, sig_pix, sig_pol, sig_t, found)
    candidates = leak_candidates
    if leak and n_found:  # new candidates, once each, in increasing pixel order
        fresh = np.empty(n_found, np.int64)
        n_fresh = 0
        for i in range(n_found):
            if not is_candidate[found[i]]:
                fresh[n_fresh] = found[i]
                n_fresh += 1
        if n_fresh:
            fresh = np.unique(fresh[:n_fresh])
            for i in range(fresh.size):
                is_candidate[fresh[i]] = True
            candidates = np.concatenate((candidates, fresh))
    # The quiet pixels' leak: the candidates due (those that fell below their band since they became candidates
    # cannot leak in this epoch and leave), then a counting pass sizes the output of the pass that leaks them.
    n_leak = 0
    leak_pix, leak_t = np.empty(0, np.int64), np.empty(0, np.int64)
    if leak and candidates.size:
        due, kept = np.empty(candidates.size, np.int64), np.empty(candidates.size, np.int64)
        n_due, n_kept = leak_due(candidates, t_start, t1, c_on, k, reference, log_filtered, hi, to_end, is_candidate, due,
                                 kept)
        if n_kept < candidates.size:
            candidates = kept[:n_kept]
        if n_due:
            count = quiet_leak(due[:n_due], t_start, t1, c_on, c_off, k, reference, log_filtered, last_event, refractory,
                               hi, lo, True, leak_pix, leak_t)
            if count:
                leak_pix, leak_t = np.empty(count, np.int64), np.empty(count, np.int64)
                n_leak = quiet_leak(due[:n_due], t_start, t1, c_on, c_off, k, reference, log_filtered, last_event,
                                    refractory, hi, lo, False, leak_pix, leak_t)
    # Signal and leak, then the shot noise that keeps clear of them.
    n_other = n_sig + n_leak
    other_pix, other_t = np.empty(n_other, np.int64), np.empty(n_other, np.int64)
    other_pix[:n_sig], other_t[:n_sig] = sig_pix[:n_sig], sig_t[:n_sig]
    other_pix[n_sig:], other_t[n_sig:] = leak_pix[:n_leak], leak_t[:n_leak]
    keep = np.ones(noise_pix.size, np.bool_)
    if noise_pix.size and refractory > 0:
        clear_noise(other_pix, other_t, noise_pix, noise_t, noise_last, refractory, scratch, keep)
        for j in range(noise_pix.size):
            if keep[j] and noise_t[j] > last_event[noise_pix[j]]:
                last_event[noise_pix[j]] = noise_t[j]
    n_all = n_other + np.count_nonzero(keep)
    out_pix, out_pol, out_t = np.empty(n_all, np.int64), np.empty(n_all, np.uint8), np.empty(n_all, np.int64)
    n = 0
    for i in range(n_sig):
        if not (has_dead and dead[sig_pix[i]]):
            out_pix[n], out_pol[n], out_t[n] = sig_pix[i], sig_pol[i], sig_t[i]
            n += 1
    for i in range(n_leak):
        if not (has_dead and dead[leak_pix[i]]):
            out_pix[n], out_pol[n], out_t[n] = leak_pix[i], 1, leak_t[i]
            n += 1
    for j in range(noise_pix.size):
        if keep[j] and not (has_dead and dead[noise_pix[j]]):
            out_pix[n], out_pol[n], out_t[n] = noise_pix[j], noise_pol[j], noise_t[j]
            n += 1
    # The sort key, (t, pixel, polarity) in one int64 (equal keys are identical events); numpy's argsort, vectorised,
    # sorts it faster than a compiled loop.
    key = np.empty(n, np.int64)
    for i in range(n):
        key[i] = ((out_t[i] - t0) * size + out_pix[i]) * 2 + out_pol[i]
    return out_pix[:n], out_pol[:n], out_t[:n], key, active, candidates


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels on tiny inputs."""
    f8, i8 = np.float64, np.int64
    z2 = np.zeros((2, 2))
    shade_compose((0, 1, 0, 1), (0, 1, 0, 1), np.zeros(8), 2, np.zeros((2, 2), np.int32), z2, z2.copy(),
                  (0.0, 1.0, 2.0, 0.0, 1.0, 2.0), z2, z2.copy(), 1.0, np.ones((2, 2)), np.zeros((4, 4)), 1,
                  np.zeros((2, 2)), True, 1e-4, np.zeros((1, 1), np.bool_), np.zeros((1, 1)))
    sensor_block(0, 0, 2, np.ones((1, 1), np.bool_), np.zeros((1, 1)), 1e-3, np.zeros(4), np.zeros(4), np.ones(4),
                 -np.ones(4), np.zeros(4), 10.0, 0.0, np.zeros(4, np.bool_), 0.5, 0.25, 0.25, 1e-4, np.zeros(1, i8),
                 np.zeros(1, f8), np.zeros(1, f8), np.zeros(1, i8))
    sensor_list(np.zeros(1, i8), np.zeros(1), np.zeros(1, i8), (0, 0, 0, 0), 2, np.zeros(4, i8), 1, np.zeros(4),
                np.zeros(4), np.ones(4), -np.ones(4), np.zeros(4), 10.0, 0.0, 0.5, 0.25, 0.25, 1e-4, np.zeros(2, i8),
                np.zeros(2, f8), np.zeros(2, f8), np.zeros(2, i8))
    one = np.ones(1)
    crossings(0, 10, np.zeros(1, i8), 0 * one, one, 0 * one, 0.2 * one, 0.2 * one, 1e-9 * one, True, 0, 10.0,
              one.copy(), -one, np.zeros(1, i8), 300, np.zeros(8, i8), np.zeros(8, np.uint8), np.zeros(8, i8),
              np.zeros(1, i8))
    epoch_leak_candidates(one, 1.0, one, one.copy(), np.zeros(1, i8))
    leak_due(np.zeros(1, i8), 0, 10, 0.2 * one, 1e-9 * one, 0 * one, one, one.copy(), 10.0, np.ones(1, np.bool_),
             np.zeros(1, i8), np.zeros(1, i8))
    for count_only in (True, False):
        quiet_leak(np.zeros(1, i8), 0, 10, 0.2 * one, 0.2 * one, 1e-9 * one, 0 * one, one.copy(), np.zeros(1, i8), 300,
                   one.copy(), -one, count_only, np.zeros(1, i8), np.zeros(1, i8))
    rim_change(np.zeros(1, i8), np.full((1, 2), 2.0), np.zeros((1, 2), i8), np.ones((1, 2), i8), one, 0 * one, one,
               0 * one, 3 * one, 0, 4, 1.0, np.zeros((1, 4, 4)), np.zeros(1, i8), 4, np.zeros(16), np.zeros(16, i8),
               np.zeros(16))
    moved_markers(np.ones((1, 2)), np.ones((1, 2, 2)), np.zeros((1, 2)), np.zeros((1, 2, 2)), 0.002)
    rim_moves(np.zeros(1, i8), np.full((1, 2), 3.0), np.eye(2)[None].copy(), 4, 1.0, False, np.full((1, 2), 3.0),
              np.eye(2)[None].copy(), np.eye(2)[None].copy(), np.zeros((1, 2), i8), np.zeros(1), np.ones(1),
              np.zeros((1, 8, 8)), 8, 0, 0, 24, 24, np.zeros(576))
    touch_luminance(np.zeros(1, i8), np.zeros(1, i8), np.zeros(1), 0.1, 0.9, 1.0, np.zeros(1), np.zeros(1, i8),
                    (0, 0, 0, 0), 1, np.zeros(1, i8))
    compose_list(np.zeros(1, i8), 1, np.zeros(1, i8), np.ones(1), np.ones(1), np.zeros(1), True, 1e-4,
                 np.zeros(1, i8), np.zeros(1))
    clear_noise(np.zeros(1, i8), np.zeros(1, i8), np.ones(1, i8), np.ones(1, i8), np.zeros(1, i8), 300, np.zeros(4, i8),
                np.zeros(1, np.bool_))
    for has_block in (False, True):
        sensor_step(0, 10, np.zeros(1, i8), np.zeros(1), np.zeros(1, i8), has_block, 0, 0, np.ones((1, 1), np.bool_),
                    np.zeros((1, 1)), 1e-3, 2, np.zeros(4, i8), 1, np.zeros(4), np.zeros(4), np.ones(4), -np.ones(4),
                    np.zeros(4, np.bool_), 0.5, 0.25, 0.25, 1e-4, np.zeros(4), 0.2 * np.ones(4), 0.2 * np.ones(4),
                    1e-9 * np.ones(4), True, 0, 0.0, 10.0, np.zeros(4, i8), 300, 0.2, 0.2, 1e-9, np.zeros(1, i8),
                    np.zeros(4, np.bool_), np.ones(1, i8), np.ones(1, np.uint8), np.ones(1, i8), np.zeros(1, i8),
                    np.zeros(4, i8), np.zeros(4, np.bool_), has_block)
    slope_magnitude(np.zeros((2, 2)), 1.0, 1.0, np.zeros((2, 2)))
    above_box(np.zeros((2, 2)), 0.5)
