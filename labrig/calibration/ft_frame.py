"""The F/T sensor's axes in the gel frame, and its readings as the force on the gel.

The one sign convention of labrig's forces: **the force on the gel, in the gel frame, N** (a press
has Fz < 0; docs/architecture.md, Frames and signs). The F/T sensor carries the indenter and reads
the force on it, in its own axes; the rig registration (``rig-registration.toml``, ``[ft_axes]``)
turns its axes into the gel frame, and the sign flips.
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
from labrig.frames import rotvec_to_matrix
from labrig.recording import Recording

F64 = npt.NDArray[np.float64]


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


def force_on_gel_ranges(recording: Recording, calibration_dir: str | Path | None = DEFAULT_CALIBRATION_DIR
                        ) -> dict[str, Any]:
    """The range of the F/T sensor's tared force as the force on the gel, gel frame (N), per axis, as summary keys
    ``force_on_gel_{x,y,z}_{min,max}_n``, with ``force_on_gel_ft_axes`` naming where the F/T axes came from."""
    rotation, source = ft_axes_in_gel(recording, calibration_dir)
    out: dict[str, Any] = {"force_on_gel_ft_axes": source}
    on_gel = ft_on_gel_n(recording.ft()["force_n"], rotation) if recording.rows("ft") else np.zeros((0, 3))
    for i, axis in enumerate("xyz"):
        out[f"force_on_gel_{axis}_min_n"] = float(on_gel[:, i].min()) if len(on_gel) else None
        out[f"force_on_gel_{axis}_max_n"] = float(on_gel[:, i].max()) if len(on_gel) else None
    return out
