"""The virtual rig's markers as printed: what the renderer draws and what the truth describes.

``[sim.markers]`` (:mod:`labrig.sim.imperfections`) perturbs the nominal lattice: placement
errors, per-marker diameters and contrasts, missing markers. :class:`PrintedLayout`
carries that through the rig:

* the renderer draws the printed markers only, at their printed rest centres, with
  their own diameters and contrasts (:meth:`renderer_options`, :meth:`drawn`);
* ``/truth/markers`` keeps one column per lattice marker; a missing marker's
  positions are NaN (:meth:`mask_truth`);
* ``/truth/marker_forces``: with any imperfection, each marker's cell is the set of
  surface nodes nearer to it than to any other printed marker (inside the lattice's
  outer cell boundary), so the cells still tile the marker area and the forces still
  sum to the net force; a missing marker's force is NaN. The ideal lattice keeps its
  regular pitch x pitch cells.
"""

from __future__ import annotations

from typing import TypedDict, TypeVar

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from labrig.config import RigConfig
from labrig.sim.imperfections import PrintedMarkers, printed_markers
from labrig.sim.truth_config import sim_config

F64 = npt.NDArray[np.float64]
FloatArray = TypeVar("FloatArray", bound=npt.NDArray[np.floating])


class RendererOptions(TypedDict, total=False):
    """The printed markers' keyword arguments for :class:`~labrig.sim.optics.Renderer`."""

    marker_xyz_mm: F64
    marker_diameter_mm: F64
    marker_contrast: F64


class PrintedLayout:
    """The printed markers of a rig (see the module docstring)."""

    def __init__(self, rig: RigConfig) -> None:
        self.ideal = sim_config(rig).markers.ideal
        self.markers: PrintedMarkers = printed_markers(sim_config(rig).markers, rig.markers.rest_positions_mm(),
                                                       rig.markers.diameter_mm)
        printed = self.markers.printed
        #: Indices of the printed markers, or None when every marker is printed.
        self.drawn_index: npt.NDArray[np.int64] | None = None if printed.all() else np.flatnonzero(printed)
        self._tree_index = np.flatnonzero(printed)
        self._tree: cKDTree | None = None

    @property
    def rest_mm(self) -> F64:
        """(N, 3) printed rest centres, gel mm (a missing marker's: where it would have been)."""
        return self.markers.rest_mm

    def renderer_options(self) -> RendererOptions:
        """Keyword arguments for :class:`~labrig.sim.optics.Renderer` (none for the ideal lattice)."""
        if self.ideal:
            return {}
        printed = self.markers.printed
        return {"marker_xyz_mm": self.rest_mm[printed], "marker_diameter_mm": self.markers.diameter_mm[printed],
                "marker_contrast": self.markers.contrast[printed]}

    def drawn(self, markers_mm: F64) -> F64:
        """The printed markers' rows of (N, 3) marker centres."""
        return markers_mm if self.drawn_index is None else markers_mm[self.drawn_index]

    def mask_truth(self, values: FloatArray, axis: int = 0) -> FloatArray:
        """``values`` with NaN at the missing markers along ``axis`` (in place; returned)."""
        if self.drawn_index is not None:
            index: list[slice | npt.NDArray[np.bool_]] = [slice(None)] * values.ndim
            index[axis] = ~self.markers.printed
            values[tuple(index)] = np.nan
        return values

    def cells(self, x_mm: F64, y_mm: F64, lattice_cells: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        """Marker cell of each node (len(y), len(x)) at gel x_mm, y_mm; ``lattice_cells`` the regular cells (-1 outside)."""
        if self.ideal:
            return lattice_cells
        if self._tree is None:
            self._tree = cKDTree(self.rest_mm[self._tree_index, :2])
        xx, yy = np.meshgrid(x_mm, y_mm)
        _, nearest = self._tree.query(np.stack([xx.ravel(), yy.ravel()], axis=1))
        return np.where(lattice_cells >= 0, self._tree_index[nearest].reshape(xx.shape), -1)
