"""What only a simulation knows, as recording streams under ``/truth``.

* ``truth/markers``: true marker centres, gel frame (mm) and image (px), 1 kHz.
* ``truth/contact``: indentation depth, tip position, net force on the gel and
  centre of pressure (gel frame), and whether the contact slides as a whole (gross
  slip), at every quasi-static solve.
* ``truth/marker_forces``: traction integrated over each marker's cell (N, gel
  frame, force on the gel), at every solve: the dense force field.
* ``truth/depth``: the true normal displacement (mm, into the gel) and the
  contact mask on the network grid (the ROI resized to 90 x 112), at every solve.

The network grid (:mod:`labrig.physics.grid`) maps cell centres to sensor
pixels linearly over the ROI and from there to the gel surface at rest through
the true camera; the mapping is stored with the stream.
"""

from __future__ import annotations

from labrig.physics.grid import GRID_SHAPE
from labrig.recording.codecs import TRUTH_CODEC
from labrig.recording.schema import Column, StreamSpec


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
            codec=TRUTH_CODEC,
        ),
        StreamSpec(
            "truth/contact",
            (
                Column("t_host_us", "<i8", "us", "host time of the solve"),
                Column("indentation_mm", "<f4", "mm", "depth of the indenter tip below the surface"),
                Column("tip_mm", "<f4", "mm", "indenter tip, gel frame", (3,)),
                Column("force_n", "<f4", "N", "net force on the gel, gel frame", (3,)),
                Column("centre_of_pressure_mm", "<f4", "mm", "centre of pressure, gel frame", (3,)),
                Column("sliding", "u1", "", "1 while the whole contact slides (gross slip: the indenter drags it)"),
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
            codec=TRUTH_CODEC,
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
            codec=TRUTH_CODEC,
        ),
    )
