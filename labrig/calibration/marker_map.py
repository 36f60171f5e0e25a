"""The markers as printed: measured rest positions, missing markers and residuals against the nominal lattice.

The extrinsic calibration measures every marker's centre in the LED-blink frame
(:mod:`labrig.calibration.extrinsics`). A real gel's markers are placed by hand or by
a stencil: each sits somewhat off its nominal lattice site, and some may be missing.
:class:`MarkerMap` keeps what was measured, per marker in the rig's node order
(row-major from -y, -x of the gel frame):

* ``nominal_px``: the nominal lattice projected through the fitted pose (sensor px);
* ``measured_px``: the measured centre (sensor px), NaN where the marker is missing;
* ``in_pose``: whether the marker was used to fit the pose (a marker printed far off
  its site is measured but left out of the pose);
* ``residual_mm``: the measured centre back-projected to the gel plane (z = 0) less
  the nominal site (gel frame mm), NaN where missing: the printing error.

The pipeline starts tracking and displacements from :attr:`MarkerMap.rest_px` (the
measured centre, the nominal projection only where nothing was measured) and skips
:attr:`MarkerMap.missing` markers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
import numpy.typing as npt

from labrig.physics.camera import CameraModel

Array = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class MarkerResidual:
    """One marker's printing error: measured centre less its nominal site."""

    index: int  # node order
    row: int
    col: int
    residual_px: float  # |measured - nominal projection|, sensor px
    residual_mm: float  # |measured - nominal| on the gel plane, mm


@dataclass(frozen=True)
class MarkerMap:
    """Per-marker rest positions as measured by the extrinsic calibration (module docstring)."""

    cols: int
    nominal_px: Array  # (M, 2)
    measured_px: Array  # (M, 2), NaN where missing
    in_pose: BoolArray  # (M,)
    residual_mm: Array  # (M, 2), NaN where missing

    def __post_init__(self) -> None:
        m = len(self.nominal_px)
        for name, shape in (("nominal_px", (m, 2)), ("measured_px", (m, 2)), ("in_pose", (m,)), ("residual_mm", (m, 2))):
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"MarkerMap.{name} has shape {np.shape(getattr(self, name))}, expected {shape}")
        if self.cols < 1 or m % self.cols:
            raise ValueError(f"{m} markers do not make rows of {self.cols}")

    @classmethod
    def measure(cls, cols: int, nominal_px: npt.ArrayLike, measured_px: npt.ArrayLike, in_pose: npt.ArrayLike,
                camera: CameraModel, nominal_mm: npt.ArrayLike) -> MarkerMap:
        """The map from measured centres, their nominal projections and sites (gel mm), through ``camera``."""
        measured = np.asarray(measured_px, np.float64)
        residual_mm = np.full((len(measured), 2), np.nan)
        found = np.isfinite(measured).all(axis=1)
        if found.any():
            on_gel = camera.backproject_to_plane(measured[found], 0.0)[:, :2]
            residual_mm[found] = on_gel - np.asarray(nominal_mm, np.float64)[found, :2]
        return cls(cols, np.asarray(nominal_px, np.float64), measured, np.asarray(in_pose, bool) & found, residual_mm)

    @classmethod
    def nominal(cls, cols: int, nominal_px: npt.ArrayLike) -> MarkerMap:
        """A map that knows only the nominal lattice: every marker present, rest = nominal projection."""
        px = np.asarray(nominal_px, np.float64)
        return cls(cols, px, px.copy(), np.ones(len(px), bool), np.zeros((len(px), 2)))

    @property
    def n_markers(self) -> int:
        return len(self.nominal_px)

    @property
    def missing(self) -> BoolArray:
        """(M,) True where no marker was measured (never printed, or not visible)."""
        return cast(BoolArray, ~np.isfinite(self.measured_px).all(axis=1))

    @property
    def missing_indices(self) -> list[int]:
        return [int(i) for i in np.flatnonzero(self.missing)]

    @property
    def rest_px(self) -> Array:
        """(M, 2) where tracking starts: the measured centre, the nominal projection where missing."""
        return np.where(self.missing[:, None], self.nominal_px, self.measured_px)

    @property
    def residual_px(self) -> Array:
        """(M, 2) measured less nominal projection, sensor px; NaN where missing."""
        return self.measured_px - self.nominal_px

    @property
    def residual_norm_px(self) -> Array:
        return np.linalg.norm(self.residual_px, axis=1)

    @property
    def residual_norm_mm(self) -> Array:
        return np.linalg.norm(self.residual_mm, axis=1)

    def row_col(self, index: int) -> tuple[int, int]:
        return divmod(int(index), self.cols)

    def worst(self, count: int = 5) -> list[MarkerResidual]:
        """The ``count`` markers farthest from their nominal site on the gel (missing ones left out)."""
        norm_mm, norm_px = self.residual_norm_mm, self.residual_norm_px
        order = [int(i) for i in np.argsort(-np.nan_to_num(norm_mm, nan=-1.0), kind="stable") if np.isfinite(norm_mm[i])]
        return [MarkerResidual(i, *self.row_col(i), float(norm_px[i]), float(norm_mm[i])) for i in order[:count]]

    def summary(self, worst: int = 5) -> dict[str, object]:
        """Stable keys for ``--json``: missing markers and the residuals (px on the sensor, mm on the gel)."""
        found = ~self.missing

        def stat(values: Array, fn: str) -> float:
            v = values[found]
            if not v.size:
                return float("nan")
            return float(np.sqrt(np.mean(v**2))) if fn == "rms" else float(np.max(v))

        return {
            "markers_missing": self.missing_indices,
            "markers_missing_row_col": [list(self.row_col(i)) for i in self.missing_indices],
            "markers_out_of_pose": [int(i) for i in np.flatnonzero(found & ~self.in_pose)],
            "residual_rms_px": stat(self.residual_norm_px, "rms"), "residual_max_px": stat(self.residual_norm_px, "max"),
            "residual_rms_mm": stat(self.residual_norm_mm, "rms"), "residual_max_mm": stat(self.residual_norm_mm, "max"),
            "worst_residuals": [{"index": r.index, "row": r.row, "col": r.col, "residual_px": r.residual_px,
                                 "residual_mm": r.residual_mm} for r in self.worst(worst)],
        }
