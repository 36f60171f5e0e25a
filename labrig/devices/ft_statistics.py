"""What a stretch of Bota F/T samples says about the sensor: rate, mean, noise and range per axis.

Sans-I/O: :func:`sinc_length_for_rate` picks the filter setting of a sample rate before the
sensor is configured, :func:`ft_statistics` summarizes the samples read (``labrig ft``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from labrig.devices.bota_protocol import ADC_BASE_RATE_HZ, SINC_LENGTH_MAX, SINC_LENGTH_MIN
from labrig.devices.bota_stream import FtSample
from labrig.errors import LabrigError

#: The six axes: (key, name, unit key, unit). Forces in N, torques in N m, sensor frame.
FT_AXES = (("fx", "Fx", "n", "N"), ("fy", "Fy", "n", "N"), ("fz", "Fz", "n", "N"),
           ("tx", "Tx", "nm", "N m"), ("ty", "Ty", "nm", "N m"), ("tz", "Tz", "nm", "N m"))


class SampleRateError(LabrigError, ValueError):
    """A sample rate the sensor's sinc filter cannot give."""


def sinc_length_for_rate(rate_hz: float) -> int:
    """The sinc filter length whose rate (``ADC_BASE_RATE_HZ / length``) is ``rate_hz`` within 0.5 %.

    Raises :class:`SampleRateError` (its message reads after the option's name: "must be ...").
    """
    if rate_hz > 0:
        sinc = round(ADC_BASE_RATE_HZ / rate_hz)
        if SINC_LENGTH_MIN <= sinc <= SINC_LENGTH_MAX and abs(ADC_BASE_RATE_HZ / sinc - rate_hz) <= 0.005 * rate_hz:
            return sinc
    raise SampleRateError(f"must be {ADC_BASE_RATE_HZ} / N for N in {SINC_LENGTH_MIN}..{SINC_LENGTH_MAX} "
                          f"(e.g. 800, 400, 200, 100, 50, 25), got {rate_hz:g}")


@dataclass(frozen=True)
class AxisStatistics:
    """One axis over the samples (N or N m; None without samples)."""

    mean: float | None
    std: float | None
    min: float | None
    max: float | None


@dataclass(frozen=True)
class FtStatistics:
    """Samples read, their rate from the host stamps (Hz; 0 with fewer than two) and each axis of :data:`FT_AXES`."""

    samples: int
    rate_hz: float
    axes: dict[str, AxisStatistics]


def ft_statistics(samples: Sequence[FtSample]) -> FtStatistics:
    """Rate (from the host stamps), mean, noise (std) and range of each force and torque axis."""
    data = np.array([(*s.force_n, *s.torque_nm) for s in samples], dtype=np.float64).reshape(-1, 6)
    t_ns = np.array([s.t_host_ns for s in samples], dtype=np.int64)
    span_s = (t_ns[-1] - t_ns[0]) / 1e9 if len(t_ns) > 1 else 0.0
    axes = {}
    for i, (key, _, _, _) in enumerate(FT_AXES):
        column = data[:, i]
        if len(column) == 0:
            axes[key] = AxisStatistics(None, None, None, None)
        else:
            axes[key] = AxisStatistics(float(column.mean()), float(column.std()), float(column.min()), float(column.max()))
    return FtStatistics(len(samples), (len(samples) - 1) / span_s if span_s > 0 else 0.0, axes)
