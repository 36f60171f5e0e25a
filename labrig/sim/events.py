"""The DVS pixel model: log-intensity change detection with noise, over the ROI pixels.

Model (after ESIM and v2e, as summarised in the shared reference notes, events.md section 8). Per pixel:

* **Log intensity** ``L = log(eps + I)``, I the linear intensity in [0, 1],
  eps = 1e-3 (ESIM's default).
* **Thresholds** ``C_on``, ``C_off`` drawn once per pixel from
  N(threshold, threshold_sigma), clamped >= 0.01 (v2e), in ln units.
* **Photoreceptor** first-order low-pass ``tau dLf/dt = L - Lf`` with
  ``tau = 1 / (2 pi cutoff_hz)``, the same for all intensities (v2e's
  intensity-dependent bandwidth is not modelled); cutoff_hz <= 0 disables it.
  Between two render steps the input L ramps linearly, Lf is advanced by the
  exact solution for a ramp, and Lf is taken linear in time between the steps.
* **Change detection** with a memorised reference R and a leak drift:
  ``D(t) = Lf(t) - R + k (t - t_start)``, ``k = leak_rate_hz * C_on`` per
  second, so a quiet pixel makes an ON event every 1 / leak_rate_hz seconds
  (v2e's leak, without its per-pixel rate spread and jitter). An ON event
  each time D reaches C_on (R += C_on), an OFF event each time it reaches
  -C_off (R -= C_off); several crossings in one step give several events,
  their times interpolated linearly between the steps and floored to whole
  microseconds. Pixels start in the leak's steady state, D uniform in
  [0, C_on) (or in [-C_off, C_on) without leak), so leak events are not synchronised.
* **Refractory period** (ESIM semantics): R follows every crossing, but an
  event closer than ``refractory_us`` (rounded up to whole us) to the pixel's
  last emitted event is dropped.
* **Shot noise**: Poisson events at ``shot_noise_rate_hz`` per pixel in total,
  half ON and half OFF, uniform in time, leaving R unchanged; one that would
  fall within the refractory period of another event of its pixel is dropped.
* **Dead pixels** (optional ``dead`` mask): a dead pixel emits nothing (its
  events, signal and noise alike, are dropped at the output).

Cost: a step updates only the pixels given to it plus the pixels whose
low-pass has not settled (|Lf - L| > settle_log); a dense block of changed
pixels (a re-shaded membrane) is updated on contiguous slices. The exact
crossing arithmetic runs only on pixels whose filtered log intensity left a
per-pixel band in which no crossing (nor leak) can happen before the end of
the current leak epoch (0.1 s of sim time). A quiet pixel's next leak time,
``t_start + (C_on + R - Lf) / k``, is computed for the few pixels that may
leak within the epoch, not stored per input change; shot noise is sampled as
one Poisson count for the array over ``NOISE_HORIZON_US`` ahead (the steps
take theirs from it). Random numbers come from one numpy
Generator: the same seed and inputs give byte-identical events. Times are
integer microseconds of the sim's world time.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig
from labrig.eventtypes import EVENT_DTYPE
from labrig.sim import _render_kernels as _k
from labrig.sim.pixels import PixelBlock
from labrig.sim.truth_config import sim_config

Array = npt.NDArray[np.float64]
Index = npt.NDArray[np.int64]

#: One CD event: sensor pixel x, y; polarity p (1 ON, 0 OFF); time t (us).

_NEVER_US = -(2**62)
_NO_BLOCK = np.zeros((0, 0), dtype=np.bool_)
_NO_BLOCK_VALUES = np.zeros((0, 0))
_NO_DEAD = np.zeros(0, dtype=np.bool_)
_NO_PIXELS_I = np.zeros(0, dtype=np.int64)
_NO_POLARITY = np.zeros(0, dtype=np.uint8)
#: Shot noise is drawn this far ahead at a time (us of sim time; offsets in it fit 16 bits, sorted by radix).
NOISE_HORIZON_US = 2**16


@dataclass(frozen=True)
class EventParams:
    """Pixel model parameters: thresholds in ln units, times in us, rates in Hz per pixel."""

    threshold_on: float = 0.22
    threshold_off: float = 0.22
    threshold_sigma: float = 0.03
    refractory_us: float = 300.0
    cutoff_hz: float = 800.0
    leak_rate_hz: float = 0.05
    shot_noise_rate_hz: float = 0.05
    eps: float = 1e-3
    settle_log: float = 1e-4
    leak_epoch_us: int = 100_000

    @classmethod
    def from_rig(cls, rig: RigConfig) -> EventParams:
        ev = sim_config(rig).events
        return cls(
            threshold_on=ev.threshold_on,
            threshold_off=ev.threshold_off,
            threshold_sigma=ev.threshold_sigma,
            refractory_us=ev.refractory_us,
            cutoff_hz=ev.cutoff_hz,
            leak_rate_hz=ev.leak_rate_hz,
            shot_noise_rate_hz=ev.shot_noise_rate_hz,
        )

    def noiseless(self) -> EventParams:
        """The same pixel without leak, shot noise or refractory period."""
        return replace(self, leak_rate_hz=0.0, shot_noise_rate_hz=0.0, refractory_us=0.0)


def make_events(x: npt.ArrayLike, y: npt.ArrayLike, p: npt.ArrayLike, t: npt.ArrayLike) -> npt.NDArray[np.void]:
    """A structured event array (:data:`EVENT_DTYPE`) from its columns."""
    x = np.asarray(x)
    out = np.empty(x.size, dtype=EVENT_DTYPE)
    out["x"], out["y"], out["p"], out["t"] = x, y, p, t
    return out


class EventSensor:
    """Stateful DVS pixels over a width x height window whose top-left pixel is sensor (x0, y0).

    Pixel indices are flat, row-major in the window: ``(y - y0) * width + (x - x0)``.

    Implementation notes (the model is as in the module docstring):

    * Per step, only the given pixels and the unsettled ones are updated; a
      dense :class:`~labrig.sim.pixels.PixelBlock` of changed pixels is updated
      on contiguous slices of the state (no gathers).
    * The exact crossing arithmetic runs only on pixels whose filtered log
      intensity left a per-pixel band that no crossing can happen inside until
      the end of the current leak epoch. The band is kept free of time
      (``hi = R + C_on``, ``lo = R - C_off``, less a margin, refreshed at each
      event of the pixel) and the leak up to the epoch's ends is added to the
      pixel's value where it is compared, so a new epoch rewrites no band.
    * A quiet pixel's next leak time is ``t_start + (C_on + R - Lf) / k``; it
      is computed when needed (pixels that may leak within the epoch are
      candidates) instead of being stored and updated at every input change.
    """

    def __init__(
        self,
        params: EventParams,
        width: int,
        height: int,
        initial_intensity: npt.ArrayLike,
        *,
        x0: int = 0,
        y0: int = 0,
        t_us: int = 0,
        seed: int = 0,
        dead: npt.ArrayLike | None = None,
    ) -> None:
        """``dead``: an optional (height, width) boolean mask of pixels that never emit an event."""
        self.params, self.width, self.height, self.x0, self.y0 = params, width, height, x0, y0
        n = width * height
        self.dead: npt.NDArray[np.bool_] | None = None
        if dead is not None:
            mask = np.asarray(dead, dtype=bool)
            if mask.shape != (height, width):
                raise ValueError(f"the dead-pixel mask is {mask.shape}, not (height, width) = ({height}, {width})")
            self.dead = mask.ravel() if mask.any() else None
        intensity = np.asarray(initial_intensity, dtype=np.float64).ravel()
        if intensity.size != n:
            raise ValueError(f"initial_intensity has {intensity.size} values, not {width}x{height}")
        self.rng = np.random.default_rng(seed)
        p = params
        self.c_on = np.maximum(self.rng.normal(p.threshold_on, p.threshold_sigma, n), 0.01)
        self.c_off = np.maximum(self.rng.normal(p.threshold_off, p.threshold_sigma, n), 0.01)
        self.t_us = int(t_us)
        self._t_start_us = int(t_us)
        self.log_input = np.log(p.eps + intensity)
        self.log_filtered = self.log_input.copy()
        u = self.rng.random(n)
        d0 = u * self.c_on if p.leak_rate_hz > 0 else -self.c_off + u * (self.c_on + self.c_off)
        self.reference = self.log_filtered - d0
        self.last_event_us = np.full(n, _NEVER_US, dtype=np.int64)
        self._refractory_us = int(np.ceil(p.refractory_us)) if p.refractory_us > 0 else 0
        #: Leak drift per pixel, ln units per us (D grows by k per us).
        self._k = p.leak_rate_hz * 1e-6 * self.c_on if p.leak_rate_hz > 0 else np.zeros(n)
        self._active = np.empty(0, dtype=np.int64)
        self._is_active = np.zeros(n, dtype=bool)
        self._scratch = np.zeros(n, dtype=np.int64)
        self._mark = np.zeros(n, dtype=np.int64)
        self._stamp = 0
        # Leak epoch [start, end] (us): no pixel inside its band crosses before the end (_k.outside_band).
        self._epoch_start_us = -np.inf
        self._epoch_end_us = -np.inf
        self._c_min = float(min(self.c_on.min(initial=1.0), self.c_off.min(initial=1.0)))
        self._c_max = float(max(self.c_on.max(initial=0.0), self.c_off.max(initial=0.0)))
        self._k_max = float(np.max(self._k, initial=0.0))
        self._hi = self.reference + (self.c_on - 2e-9)
        self._lo = self.reference + (2e-9 - self.c_off)
        self._leak_candidates = np.empty(0, dtype=np.int64)
        self._is_candidate = np.zeros(n, dtype=bool)
        # Shot noise drawn ahead: (pixel, polarity, t) sorted by t, covering [_noise_from_us, _noise_until_us).
        self._noise: tuple[Index, npt.NDArray[np.uint8], Index] = (_NO_PIXELS_I, _NO_POLARITY, _NO_PIXELS_I)
        self._noise_from_us = self._noise_until_us = self.t_us

    @classmethod
    def from_rig(
        cls, rig: RigConfig, initial_intensity: npt.ArrayLike, *, t_us: int = 0, seed: int = 0,
        params: EventParams | None = None, dead: npt.ArrayLike | None = None,
    ) -> EventSensor:
        """Pixels over the rig's ROI with the rig's event parameters (or ``params``); ``dead``: (height, width) mask."""
        roi = rig.roi
        return cls(
            params or EventParams.from_rig(rig),
            roi.width_px,
            roi.height_px,
            initial_intensity,
            x0=roi.x0_px,
            y0=roi.y0_px,
            t_us=t_us,
            seed=seed,
            dead=dead,
        )

    @property
    def size(self) -> int:
        return self.width * self.height

    def step(
        self,
        t0_us: int,
        t1_us: int,
        pixel_indices: npt.ArrayLike,
        new_intensity: npt.ArrayLike,
        *,
        block: PixelBlock | None = None,
    ) -> npt.NDArray[np.void]:
        """Advance from t0_us (the sensor's current time) to t1_us; return the events (EVENT_DTYPE) sorted by t.

        ``pixel_indices`` (distinct flat window indices) get ``new_intensity``
        (linear, [0, 1]) at t1_us, ramping from their previous value; so do the
        changed pixels of ``block`` (window coordinates, disjoint from
        ``pixel_indices``); all other pixels keep theirs.
        """
        t0_us, t1_us = int(t0_us), int(t1_us)
        if t0_us != self.t_us or t1_us <= t0_us:
            raise ValueError(f"step must go forward from the sensor time {self.t_us} us, not {t0_us} -> {t1_us} us")
        pixels = np.asarray(pixel_indices, dtype=np.int64).ravel()
        log_new = np.log(self.params.eps + np.asarray(new_intensity, dtype=np.float64).ravel())
        noise_pix, noise_pol, noise_t, noise_last = self._sample_shot_noise(t0_us, t1_us)
        self._start_epoch(t0_us, t1_us)
        p = self.params
        a, b, c = self._filter(t1_us - t0_us)
        self._stamp += 1
        has_block = block is not None
        pix, pol, t, key, self._active, self._leak_candidates = _k.sensor_step(
            t0_us, t1_us, pixels, log_new, self._active, has_block, block.y0 if block is not None else 0,
            block.x0 if block is not None else 0, block.changed if block is not None else _NO_BLOCK,
            block.values if block is not None else _NO_BLOCK_VALUES, float(p.eps), self.width, self._mark, self._stamp,
            self.log_input, self.log_filtered, self._hi, self._lo, self._is_active, a, b, c, p.settle_log,
            self.reference, self.c_on, self.c_off, self._k, p.leak_rate_hz > 0, self._t_start_us,
            float(self._epoch_start_us), float(self._epoch_end_us), self.last_event_us, self._refractory_us,
            self._c_max, self._c_min, self._k_max, self._leak_candidates, self._is_candidate, noise_pix, noise_pol,
            noise_t, noise_last, self._scratch, _NO_DEAD if self.dead is None else self.dead, self.dead is not None,
        )
        self.t_us = t1_us
        order = np.argsort(key)
        pix, pol, t = pix[order], pol[order], t[order]
        y, x = np.divmod(pix, self.width)
        return make_events(x + self.x0, y + self.y0, pol, t)

    # -- signal ------------------------------------------------------------------------------------

    def _filter(self, dt_us: int) -> tuple[float, float, float]:
        """(a, b, c) of the low-pass step for an input ramping u0 -> u1 over dt: y1 = a y0 + b u1 + c u0 (exact)."""
        p = self.params
        if p.cutoff_hz <= 0:
            return 0.0, 1.0, 0.0
        decay = float(np.exp(-dt_us * 2 * np.pi * p.cutoff_hz * 1e-6))
        beta = (1 - decay) / (dt_us * 2 * np.pi * p.cutoff_hz * 1e-6)
        return decay, 1 - beta, beta - decay

    # -- no-crossing band and leak of quiet pixels --------------------------------------------------

    def _start_epoch(self, t0_us: int, t1_us: int) -> None:
        """At the first step past the epoch: a new epoch from t0_us and its leak candidates."""
        if t1_us <= self._epoch_end_us:
            return
        self._epoch_start_us = float(t0_us)
        self._epoch_end_us = float(max(t0_us + self.params.leak_epoch_us, t1_us))
        if self.params.leak_rate_hz <= 0:
            return
        candidates = self._scratch  # as many as pixels, free between steps
        m = _k.epoch_leak_candidates(self._k, self._epoch_end_us - self._t_start_us, self.log_filtered, self._hi,
                                     candidates)
        self._is_candidate[self._leak_candidates] = False
        self._leak_candidates = candidates[:m].copy()  # increasing, once each (an empty list without leak)
        self._is_candidate[self._leak_candidates] = True

    # -- shot noise --------------------------------------------------------------------------------

    def _sample_shot_noise(self, t0_us: int, t1_us: int) -> tuple[Index, npt.NDArray[np.uint8], Index, Index]:
        """Shot-noise events (pixel, polarity, t) of [t0_us, t1_us) and their pixels' last event time at the
        step's start.

        The noise is drawn for a horizon ahead (a Poisson count over every pixel and the horizon's
        whole microseconds, uniform times, sorted) and each step takes the events before its end:
        the same process as a draw per step, with a few draws per horizon instead of per step."""
        if self.params.shot_noise_rate_hz <= 0:
            return _NO_PIXELS_I, _NO_POLARITY, _NO_PIXELS_I, _NO_PIXELS_I
        if t0_us < self._noise_from_us:
            raise ValueError(f"shot noise is drawn up to {self._noise_from_us} us; a step from {t0_us} us is past")
        while self._noise_until_us < t1_us:
            self._draw_noise()
        pix, pol, t = self._noise
        n = int(np.searchsorted(t, t1_us))
        self._noise = (pix[n:], pol[n:], t[n:])
        self._noise_from_us = t1_us
        pix, pol, t = pix[:n], pol[:n], t[:n]
        return pix, pol, t, self.last_event_us[pix]

    def _draw_noise(self) -> None:
        """Draw the next NOISE_HORIZON_US of shot noise after what is drawn."""
        t0_us, span = self._noise_until_us, NOISE_HORIZON_US
        n = int(self.rng.poisson(self.size * self.params.shot_noise_rate_hz * span * 1e-6))
        pix = self.rng.integers(0, self.size, n)
        pol = self.rng.integers(0, 2, n, dtype=np.uint8)
        offset = np.floor(self.rng.random(n) * span).astype(np.uint16)
        order = np.argsort(offset, kind="stable")  # a radix sort on 16 bits
        old_pix, old_pol, old_t = self._noise
        self._noise = (np.concatenate((old_pix, pix[order])), np.concatenate((old_pol, pol[order])),
                       np.concatenate((old_t, t0_us + offset[order].astype(np.int64))))
        self._noise_until_us = t0_us + span
