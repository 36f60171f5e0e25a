"""What only a simulation knows, as recording streams under ``/truth``.

* ``truth/markers``: true marker centres, gel frame (mm) and image (px), 1 kHz.
* ``truth/contact``: indentation depth, tip position, net force on the gel and
  centre of pressure (gel frame), at every quasi-static solve.
* ``truth/marker_forces``: traction integrated over each marker's cell (N, gel
  frame, force on the gel), at every solve: the dense force field.
* ``truth/depth``: the true normal displacement (mm, into the gel) and the
  contact mask on the network grid (the ROI resized to 90 x 112), at every solve.

The network grid maps cell centres to sensor pixels linearly over the ROI and
from there to the gel surface at rest through the true camera
(:func:`network_grid_gel_mm`); the mapping is stored with the stream.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig
from labrig.recording.schema import Column, StreamSpec
from labrig.sim.camera import CameraModel

GRID_SHAPE = (90, 112)


def truth_streams(n_markers: int, grid_shape: tuple[int, int] = GRID_SHAPE) -> tuple[StreamSpec, ...]:
    """Stream specs to pass to the recording writer as ``extra_streams``."""
    return (
        StreamSpec(
            "truth/markers",
            (
                Column("t_host_us", "<i8", "us", "host time of the sample"),
                Column("position_mm", "<f4", "mm", "marker centres, gel frame", (n_markers, 3)),
                Column("position_px", "<f4", "px", "marker centres in the image (true camera)", (n_markers, 2)),
            ),
            chunk_rows=256,
            description="true marker positions",
        ),
        StreamSpec(
            "truth/contact",
            (
                Column("t_host_us", "<i8", "us", "host time of the solve"),
                Column("indentation_mm", "<f4", "mm", "depth of the indenter tip below the surface"),
                Column("tip_mm", "<f4", "mm", "indenter tip, gel frame", (3,)),
                Column("force_n", "<f4", "N", "net force on the gel, gel frame", (3,)),
                Column("centre_of_pressure_mm", "<f4", "mm", "centre of pressure, gel frame", (3,)),
            ),
            chunk_rows=1024,
            description="true contact state at each quasi-static solve",
        ),
        StreamSpec(
            "truth/marker_forces",
            (
                Column("t_host_us", "<i8", "us", "host time of the solve"),
                Column("force_n", "<f4", "N", "traction integrated over each marker's cell, gel frame", (n_markers, 3)),
            ),
            chunk_rows=256,
            description="true per-marker force field",
        ),
        StreamSpec(
            "truth/depth",
            (
                Column("t_host_us", "<i8", "us", "host time of the solve"),
                Column("depth_mm", "<f4", "mm", "normal displacement into the gel on the network grid", grid_shape),
                Column("contact_mask", "u1", "", "1 where the indenter touches", grid_shape),
            ),
            chunk_rows=16,
            description="true normal-displacement field on the network grid (ROI resized)",
        ),
    )


def network_grid_pixels(rig: RigConfig, grid_shape: tuple[int, int] = GRID_SHAPE) -> npt.NDArray[np.float64]:
    """Sensor-pixel coordinates (rows, cols, 2) of the network grid's cell centres over the ROI."""
    roi = rig.roi
    rows, cols = grid_shape
    x = roi.x0_px - 0.5 + (np.arange(cols) + 0.5) * roi.width_px / cols
    y = roi.y0_px - 0.5 + (np.arange(rows) + 0.5) * roi.height_px / rows
    xx, yy = np.meshgrid(x, y)
    return np.stack([xx, yy], axis=-1)


def network_grid_gel_mm(rig: RigConfig, camera: CameraModel, grid_shape: tuple[int, int] = GRID_SHAPE) -> npt.NDArray[np.float64]:
    """Gel-surface points (rows, cols, 2) at rest seen by each network-grid cell."""
    px = network_grid_pixels(rig, grid_shape).reshape(-1, 2)
    return camera.backproject_to_plane(px, 0.0)[:, :2].reshape(*grid_shape, 2)
