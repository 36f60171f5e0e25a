"""Evaluation windows and what a lab measures at them: the F/T sensor in the gel frame, the contact's position.

The paper evaluates on sequential windows of 20,000 events per test recording; each
window's end is an evaluation time. The depth network always sees the window it was
trained on (its model card's ``window_ms``) ending there, whatever the evaluation step.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.errors import LabrigError
from labrig.recording import Recording

F64 = npt.NDArray[np.float64]

PAPER_WINDOW_EVENTS = 20_000


def window_ends_us(recording: Recording, *, window_events: int | None = PAPER_WINDOW_EVENTS,
                   window_us: int | None = None) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(t0_us, t1_us) host times of sequential windows: ``window_events`` events each, or ``window_us`` long.

    Count windows are found from the event time column in one pass (no event payload is
    read); the final partial window is dropped, as in :func:`labrig.pipeline.runtime.windows`.
    """
    if (window_events is None) == (window_us is None):
        raise ValueError("give exactly one of window_events and window_us")
    end = recording.end_us()
    if window_us is not None:
        if window_us <= 0:
            raise ValueError("window_us must be positive")
        t0 = np.arange(0, end - window_us + 1, window_us, dtype=np.int64)
        return t0, t0 + window_us
    assert window_events is not None
    if window_events <= 0:
        raise ValueError("window_events must be positive")
    t = _event_times_us(recording)
    starts = np.arange(0, t.size - window_events, window_events)
    return t[starts].astype(np.int64), t[starts + window_events].astype(np.int64)


def _event_times_us(recording: Recording, chunk: int = 4_000_000) -> npt.NDArray[np.int64]:
    """Every event's host time (us), in order, read in chunks of the time column only."""
    model = recording.clock_model("camera")
    n = recording.n_events
    parts = []
    for start in range(0, n, chunk):
        t_dev = recording.column("events", "t_device_us", start, min(start + chunk, n))
        parts.append(model.to_host_us_int(t_dev))
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


# -- the F/T sensor in the gel frame ------------------------------------------------------------


def ft_axes_in_gel(recording: Recording, calibration_dir: str | Path | None = "calibration") -> tuple[F64, str]:
    """Rotation (3, 3) from the F/T sensor's axes to the gel frame, and where it came from.

    The rig registration the recording names (``extra_calibration``), else
    ``calibration_dir/rig-registration.toml``, else identity (the nominal mounting).
    """
    import json

    from labrig.calibration.registration_file import load_registration
    from labrig.frames import rotvec_to_matrix

    named = recording.attrs.get("extra_calibration", "")
    candidates = [Path(p) for p in (json.loads(named) if isinstance(named, str) and named else {})
                  if Path(p).name == "rig-registration.toml"]
    if calibration_dir is not None:
        candidates.append(Path(calibration_dir) / "rig-registration.toml")
    for path in candidates:
        if path.exists():
            section = load_registration(path).get("ft_axes", {})
            if "rotvec_rad" in section:
                return rotvec_to_matrix(np.asarray(section["rotvec_rad"], np.float64)), str(path)
    return np.eye(3), "nominal (no rig registration)"


def measured_force_on_gel_n(recording: Recording, t0_us: npt.ArrayLike, t1_us: npt.ArrayLike,
                            ft_to_gel: F64) -> F64:
    """Mean tared F/T force over each ``[t0, t1)`` as the force on the gel, gel frame, N: (W, 3).

    The sensor carries the indenter and reads the force on it; the gel feels the opposite.
    A window without a sample takes the nearest sample.
    """
    if "ft" not in recording.streams or recording.rows("ft") == 0:
        raise LabrigError(f"{recording.path}: no F/T samples; force errors need the F/T sensor's stream")
    ft = recording.ft()
    t = np.asarray(ft["t_us"], np.int64)
    order = np.argsort(t, kind="stable")
    t, force = t[order], np.asarray(ft["force_n"], np.float64)[order] @ ft_to_gel.T
    cumulative = np.vstack([np.zeros(3), np.cumsum(force, axis=0)])
    a = np.searchsorted(t, np.asarray(t0_us), "left")
    b = np.searchsorted(t, np.asarray(t1_us), "left")
    count = (b - a)[:, None]
    mean = (cumulative[b] - cumulative[a]) / np.maximum(count, 1)
    nearest = force[np.clip(b, 0, t.size - 1)]
    return -np.where(count > 0, mean, nearest)


# -- where the indenter is --------------------------------------------------------------------


def contact_centre_px(groundtruth: Any, t_us: npt.ArrayLike, camera: Any) -> F64:
    """The true contact centre projected into the camera (px) at the maps nearest ``t_us``; nan out of contact.

    The sidecar's ``anchor_gel_mm``: where the indenter first touched, from the CNC pose through the
    registration (what a lab has). The depth maps are indexed by the surface point each cell saw at
    rest, so a sheared contact stays centred there while the tip moves on; the map's centre of mass
    is compared with this point, not with the moving tip.
    """
    index = np.atleast_1d(groundtruth.nearest_index(np.asarray(t_us, np.float64)))
    anchor = np.asarray(groundtruth.anchor_gel_mm, np.float64)[index]
    surface = np.column_stack([anchor[:, 0], anchor[:, 1], np.zeros(len(anchor))])
    out = np.full((len(anchor), 2), np.nan)
    inside = np.isfinite(anchor).all(1)
    if inside.any():
        out[inside] = np.asarray(camera.project(surface[inside]), np.float64)
    return out


def camera_shortfall_s(recording: Recording) -> float:
    """How long before the protocol's last phase ends the camera's events stop (s; 0 when they do not).

    A camera stream that stalls (a lagging renderer on a loaded host, a cable) leaves windows
    without events: the evaluation says so rather than score them.
    """
    phases = recording.phases()
    if not phases:
        return 0.0
    end_us = recording.events_end_us()
    stops_us = phases[0].t_start_us if end_us is None else end_us
    return max(0.0, (phases[-1].t_end_us - stops_us) / 1e6)

