"""What a lab measures at evaluation windows: the F/T sensor's force on the gel in the gel frame,
the contact's position, and whether the camera stream covers the protocol.

The windows themselves are :func:`labrig.pipeline.windows.window_ends_us` (the paper's: sequential
windows of 20,000 events per test recording; each window's end is an evaluation time).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.calibration.ft_frame import ft_axes_in_gel, ft_on_gel_n
from labrig.errors import LabrigError
from labrig.recording import Recording

__all__ = ["contact_centre_px", "ft_axes_in_gel", "ft_on_gel_n", "measured_force_on_gel_n"]

F64 = npt.NDArray[np.float64]


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
