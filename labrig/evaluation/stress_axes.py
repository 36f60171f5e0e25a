"""The stress axes of ``labrig evaluate --stress``: what each one pushes, over which values, and what it measures.

Each axis turns one knob of the scene (a field of
:class:`labrig.evaluation.stress_scene.StressScene`) or of the pipeline (``window_ms``) away
from the default probe (a 1 mm sphere press, 0.5 mm of shear, 3 mm/s, 10 ms windows), in
order of rising stress: the first value of each grid is the least stressed, the baseline a
breakdown is measured against. The full grid is for reports; the reduced grid (the first,
a middle and the last value, about) fits a test budget.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from labrig.errors import LabrigError
from labrig.evaluation.stress_scene import StressScene

GRIDS = ("full", "reduced")
DEFAULT_WINDOW_MS = 10.0
#: What an axis can measure: marker tracking (p95 true error, px; tracks lost), forces (error, % of the force) and,
#: given a network, depth (mean error over the contact cells, mm).
METRICS = ("tracking", "forces", "depth")
#: The imperfect sensor's axes (issue 19): the printed markers and the camera's USB delivery.
SENSOR_AXES = ("marker_position", "missing_near", "missing_far", "usb_bursts")
#: Another lab's camera and light: the contrast thresholds, their ON/OFF asymmetry, the LED's slope gain,
#: the membrane's brightness, and how long a press is held.
RESPONSE_AXES = ("contrast_threshold", "on_off_ratio", "led_slope_gain", "membrane_level", "hold")


@dataclass(frozen=True)
class StressAxis:
    """One stress axis. ``knob``: the :class:`StressScene` field the value sets, or ``window_ms``."""

    key: str  # stable name (report keys, --json)
    title: str
    x_name: str  # the chart's x label
    unit: str
    unit_key: str  # the unit in JSON keys (``event_noise_hz``)
    knob: str
    full: tuple[float, ...]
    reduced: tuple[float, ...]
    metrics: tuple[str, ...]
    what: str  # how a value changes the scene, one sentence
    log_x: bool = False
    event_calibration: bool = False  # the scenes change the camera or its light: measured with and without recalibrating
    #: The reference sensor's value, on both of the grids, when the axis pushes both ways from it (None: from its first
    #: value up): the breakdown is read from it outwards, under it and above it.
    reference: float | None = None

    def __post_init__(self) -> None:
        if self.reference is not None and not (self.reference in self.full and self.reference in self.reduced):
            raise LabrigError(f"stress axis {self.key}: its reference {self.reference} must be on both grids")

    @property
    def two_sided(self) -> bool:
        """Whether the axis pushes below its reference as well as above it."""
        return self.reference is not None and self.reference > min(self.full)

    def values(self, grid: str) -> tuple[float, ...]:
        if grid not in GRIDS:
            raise LabrigError(f"stress grid must be one of {', '.join(GRIDS)}, not {grid!r}")
        return self.full if grid == "full" else self.reduced

    def scene(self, value: float, base: StressScene) -> StressScene:
        """``base`` with this axis' knob at ``value`` (unchanged for a pipeline knob)."""
        changes: dict[str, Any] = {} if self.knob == "window_ms" else {self.knob: value}
        return replace(base, **changes)

    def window_ms(self, value: float) -> float:
        return float(value) if self.knob == "window_ms" else DEFAULT_WINDOW_MS

    @property
    def json_key(self) -> str:
        return f"{self.key}_{self.unit_key}"


AXES: tuple[StressAxis, ...] = (
    StressAxis(
        "force_range", "Indentation force beyond the calibrated range", "indentation depth", "mm", "mm", "depth_mm",
        full=(0.5, 0.75, 1.0, 1.5, 2.0, 2.25), reduced=(0.5, 1.0, 2.25), metrics=("forces",),
        what="presses deeper than the gel calibration did (sphere to 1.0 mm): the virtual gel stiffens "
             "(1 + 0.6 depth / thickness); the linear inverse FEM does not, the calibrated stiffening extrapolates"),
    StressAxis(
        "speed", "Indentation and shear speed", "indenter speed", "mm/s", "mm_s", "speed_mm_s",
        full=(3.0, 6.0, 12.0, 24.0, 48.0, 96.0), reduced=(3.0, 12.0, 96.0), metrics=("tracking", "forces"), log_x=True,
        what="moves the indenter faster, normal and shear phases alike"),
    StressAxis(
        "shear_slip", "Shear until slip", "shear distance", "mm", "mm", "shear_mm",
        full=(0.25, 0.5, 1.0, 1.5, 2.0, 3.0), reduced=(0.25, 1.0, 3.0), metrics=("tracking", "forces"),
        what="shears further at 1 mm depth, through partial slip into gross slip (friction 1.0)"),
    StressAxis(
        "event_noise", "Event noise rate", "noise events", "Hz per pixel", "hz", "shot_noise_rate_hz",
        full=(0.05, 0.5, 1.0, 2.0, 5.0, 10.0), reduced=(0.05, 2.0, 10.0), metrics=("tracking", "forces"), log_x=True,
        what="raises the pixels' shot-noise rate (half ON, half OFF, uniform in time)"),
    StressAxis(
        "marker_contrast", "Marker contrast", "marker dimming", "x", "x", "marker_dimming",
        full=(1.0, 2.0, 4.0, 6.0, 8.0, 10.0), reduced=(1.0, 4.0, 10.0), metrics=("tracking", "forces"),
        what="dims the markers by this factor against the black membrane (brightness 0.9 / factor vs 0.08; "
             "at 10x a marker edge is below one event threshold)"),
    StressAxis(
        "window_length", "Window length", "window", "ms", "ms", "window_ms",
        full=(10.0, 20.0, 50.0, 100.0, 200.0), reduced=(10.0, 50.0, 200.0), metrics=("tracking", "forces"),
        log_x=True, what="lengthens the pipeline's fixed-time windows (the scene is the default probe)"),
    StressAxis(
        "clock_drift", "Clock drift without resync", "time since the last camera clock sync", "min", "min",
        "sync_age_min", full=(0.0, 1.0, 5.0, 15.0, 30.0, 60.0, 120.0), reduced=(0.0, 15.0, 120.0),
        metrics=("tracking", "forces"),
        what="maps camera time with an offset-only sync this long before the run: the camera's 35 ppm drift "
             "skews events against the F/T sensor by 2.1 ms a minute"),
    StressAxis(
        "dead_region", "Dead region of pixels", "dead square side", "mm", "mm", "dead_side_mm",
        full=(0.0, 2.0, 4.0, 6.0, 8.0, 12.0), reduced=(0.0, 4.0, 12.0), metrics=("tracking", "forces"),
        what="kills the sensor pixels of a square this wide on the gel, centred on the press"),
    StressAxis(
        "marker_position", "Marker placement error", "placement error (std per axis)", "mm", "mm", "position_error_mm",
        full=(0.0, 0.025, 0.05, 0.1, 0.2, 0.3), reduced=(0.0, 0.1, 0.3), metrics=("tracking", "forces", "depth"),
        what="prints each marker off its lattice site by a seeded normal error (std per gel axis); the pipeline takes "
             "the rest positions from an extrinsic calibration of that gel"),
    StressAxis(
        "missing_near", "Missing markers at the contact", "markers missing", "% of the grid", "pct", "missing_near_pct",
        full=(0.0, 2.0, 4.0, 6.0, 8.0, 10.0), reduced=(0.0, 4.0, 10.0), metrics=("tracking", "forces", "depth"),
        what="leaves unprinted the markers nearest the press (2 % = 3 of 156 markers, 10 % = 16); the calibration "
             "finds them, the trackers skip them and the inverse FEM condenses them"),
    StressAxis(
        "missing_far", "Missing markers away from the contact", "markers missing", "% of the grid", "pct",
        "missing_far_pct", full=(0.0, 2.0, 4.0, 6.0, 8.0, 10.0), reduced=(0.0, 4.0, 10.0),
        metrics=("tracking", "forces", "depth"),
        what="leaves unprinted markers drawn at random more than 6 mm from the press, found as at the contact"),
    StressAxis(
        "usb_bursts", "USB burst delivery", "burst period", "ms", "ms", "burst_period_ms",
        full=(0.0, 10.0, 20.0, 50.0, 100.0), reduced=(0.0, 20.0, 100.0), metrics=("tracking", "forces", "depth"),
        what="hands the camera's data to the host in USB bursts this far apart (jitter 20 % of the period); the "
             "recording's clock fit rests on the prompt pairs (lower envelope) and the trigger edges"),
    StressAxis(
        "contrast_threshold", "Contrast threshold (a less sensitive bias setting)", "contrast threshold, ON and OFF",
        "ln", "ln", "contrast_threshold", full=(0.15, 0.18, 0.22, 0.26, 0.30, 0.35, 0.40), reduced=(0.15, 0.22, 0.40),
        metrics=("forces",), event_calibration=True, reference=0.22,
        what="sets both contrast thresholds, below and above the reference camera's 0.22 ln (a more or a less sensitive "
             "bias setting); more or fewer events for the same change, measured with the thresholds recalibrated "
             "(labrig calibrate events) and with the reference camera's"),
    StressAxis(
        "on_off_ratio", "ON/OFF threshold asymmetry", "C_on / C_off", "x", "x", "on_off_ratio",
        full=(1.0, 1.15, 1.3, 1.45, 1.6), reduced=(1.0, 1.3, 1.6), metrics=("forces",), event_calibration=True,
        what="splits the thresholds about their geometric mean (0.22 ln): a change and its reversal fire unequal "
             "ON and OFF counts; measured recalibrated and with the reference camera's thresholds"),
    StressAxis(
        "led_slope_gain", "LED ring slope gain", "brightening per unit surface slope", "x", "x", "slope_gain",
        full=(1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0), reduced=(1.0, 2.5, 4.0), metrics=("forces",), event_calibration=True,
        reference=2.5,
        what="changes how much brighter a sloped membrane looks under the LED ring, dimmer or brighter than the "
             "reference 2.5: the same dent "
             "changes the log intensity more or less; measured with the light recalibrated (labrig calibrate events "
             "with its press) and with the reference light's slope response"),
    StressAxis(
        "membrane_level", "Membrane brightness", "membrane level", "of full scale", "level", "membrane_level",
        full=(0.08, 0.12, 0.16, 0.24), reduced=(0.08, 0.16, 0.24), metrics=("forces",),
        what="brightens the black membrane (the reference 0.08, markers 0.9): the markers' contrast against it falls, "
             "and so do their edges' events"),
    StressAxis(
        "hold", "Press held", "each wait", "s", "s", "wait_s",
        full=(0.1, 1.0, 5.0, 20.0, 60.0), reduced=(0.1, 5.0, 60.0), metrics=("forces",), log_x=True,
        what="holds the press still this long at each of the three waits (after the press and each shear); the "
             "brightness change since rest must hold the dent that a still gel no longer signals"),
)


def axis_named(key: str) -> StressAxis:
    for axis in AXES:
        if axis.key == key:
            return axis
    raise LabrigError(f"no stress axis {key!r}; axes: {', '.join(a.key for a in AXES)}")
