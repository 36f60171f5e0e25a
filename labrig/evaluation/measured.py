"""What a lab measures at evaluation windows: the F/T sensor's force on the gel in the gel frame,
the contact's position, and whether the camera stream covers the protocol.

The windows themselves are :func:`labrig.pipeline.windows.window_ends_us` (the paper's: sequential
windows of 20,000 events per test recording; each window's end is an evaluation time).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.calibration.registration_file import REGISTRATION_FILE, load_registration
from labrig.config import DEFAULT_CALIBRATION_DIR
from labrig.errors import LabrigError
from labrig.frames import rotvec_to_matrix
from labrig.recording import Recording

F64 = npt.NDArray[np.float64]


# -- the F/T sensor in the gel frame ------------------------------------------------------------


def ft_axes_in_gel(recording: Recording | None,
                   calibration_dir: str | Path | None = DEFAULT_CALIBRATION_DIR) -> tuple[F64, str]:
    """Rotation (3, 3) from the F/T sensor's axes to the gel frame, and where it came from.

    The rig registration the recording names (``extra_calibration``; None: no recording yet, as
    in a live run), else ``calibration_dir/rig-registration.toml``, else identity (the nominal
    mounting).
    """
    named = recording.attrs.get("extra_calibration", "") if recording is not None else ""
    candidates = [Path(p) for p in (json.loads(named) if isinstance(named, str) and named else {})
                  if Path(p).name == REGISTRATION_FILE]
    if calibration_dir is not None:
        candidates.append(Path(calibration_dir) / REGISTRATION_FILE)
    for path in candidates:
        if path.exists():
            section = load_registration(path).get("ft_axes", {})
            if "rotvec_rad" in section:
                return rotvec_to_matrix(np.asarray(section["rotvec_rad"], np.float64)), str(path)
    return np.eye(3), "nominal (no rig registration)"


def ft_on_gel_n(force_sensor_n: Sequence[float] | F64, ft_to_gel: F64) -> F64:
    """Tared F/T forces (on the indenter, sensor axes, N; (3,) or (n, 3)) as the forces on the gel in the gel frame.

    The sensor carries the indenter and reads the force on it; the gel feels the opposite.
    """
    return -(np.asarray(force_sensor_n, np.float64) @ ft_to_gel.T)


def measured_force_on_gel_n(recording: Recording, t0_us: npt.ArrayLike, t1_us: npt.ArrayLike,
                            ft_to_gel: F64) -> F64:
    """Mean tared F/T force over each ``[t0, t1)`` (host time, us) as the force on the gel, gel frame, N: (W, 3).

    A window without a sample takes the nearest sample.
    """
    if "ft" not in recording.streams or recording.rows("ft") == 0:
        raise LabrigError(f"{recording.path}: no F/T samples; force errors need the F/T sensor's stream")
    ft = recording.ft()
    t = np.asarray(ft["t_us"], np.int64)
    order = np.argsort(t, kind="stable")
    t, force = t[order], ft_on_gel_n(np.asarray(ft["force_n"], np.float64)[order], ft_to_gel)
    cumulative = np.vstack([np.zeros(3), np.cumsum(force, axis=0)])
    a = np.searchsorted(t, np.asarray(t0_us), "left")
    b = np.searchsorted(t, np.asarray(t1_us), "left")
    count = (b - a)[:, None]
    mean = (cumulative[b] - cumulative[a]) / np.maximum(count, 1)
    nearest = force[np.clip(b, 0, t.size - 1)]
    return np.where(count > 0, mean, nearest)


# -- where the indenter is --------------------------------------------------------------------


def contact_centre_px(groundtruth: Any, t_us: npt.ArrayLike, camera: Any) -> F64:
    """The true contact centre projected into the camera (px) at the maps nearest ``t_us``; nan out of contact.

    The sidecar's ``anchor_gel_mm``: where the indenter first touched, from the CNC pose through the
    registration (what a lab has). The depth maps are indexed by the surface point each cell saw at
    rest, so a sheared contact stays centred there while the tip moves on; the map's dent core
    (:func:`labrig.pipeline.forces.contact_location`) is compared with this point, not with the moving tip.
    """
    index = np.atleast_1d(groundtruth.nearest_index(np.asarray(t_us, np.float64)))
    anchor = np.asarray(groundtruth.anchor_gel_mm, np.float64)[index]
    surface = np.column_stack([anchor[:, 0], anchor[:, 1], np.zeros(len(anchor))])
    out = np.full((len(anchor), 2), np.nan)
    inside = np.isfinite(anchor).all(1)
    if inside.any():
        out[inside] = np.asarray(camera.project(surface[inside]), np.float64)
    return out
