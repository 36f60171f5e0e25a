"""The contact's anchor: where a press sits on the gel, filtered over the windows of one contact.

The depth maps are indexed by the surface point each cell saw at rest, so a sticking contact's
dent stays where the indenter first touched while the indenter shears on; it moves in this frame
only when the contact slips (or lifts off and lands elsewhere). One window's dent core
(:func:`labrig.pipeline.forces.contact_location`) locates it well when the dent is deep and poorly
when it is shallow: as the indenter rises, a 0.1 mm dent's core errs by half a millimetre.

:class:`AnchorFilter` is a Kalman filter on the anchor ``x`` (mm, gel frame, at rest) per contact:

* prediction: a random walk, ``var += slip_diffusion_mm2_s * dt`` (sticking contacts stay put);
* measurement: the window's dent core, per-axis noise ``sigma = max(noise_mm2 / peak_mm, floor_mm)``,
  the depth map's peak being the window's confidence (fitted on the paper campaign's training
  split, bundled network: the per-axis RMS error times the peak is 0.04-0.06 mm^2 from 0.05 to
  1.5 mm of peak, with a floor of about 0.045 mm; docs/evaluation.md);
* slip: a core farther from the anchor than the ``gate`` (chi-square, 2 degrees of freedom) in
  ``persist`` windows running means the anchor moved: its variance takes the innovation and the
  filter follows; a lone outlier is only down-weighted (its innovation variance scaled to the gate);
* a new contact: a core outside the gate that is surer than the anchor (its noise variance below
  the anchor's) starts the anchor again there. Only a surer anchor may call a core an outlier: an
  anchor begun on a faint dimple before the press would otherwise hold the press's first core
  hundreds of pixels away (a paper-only network that dimples before contact: 4.23 px on the test
  split, 2.31 px with this rule; the bundled network unchanged).

A window without a dent ends the contact; the next dent starts a new one from its own core.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.physics.camera import CameraModel

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class AnchorParams:
    """The filter's noise model; lengths in mm of the gel frame at rest, times in s."""

    noise_mm2: float = 0.048  # a core's per-axis error times the map's peak depth
    floor_mm: float = 0.045  # the core's per-axis error on deep dents
    slip_diffusion_mm2_s: float = 1e-3  # the anchor's random walk between windows
    gate: float = 9.21  # chi-square, 2 dof, 99 %: a core this improbable is an outlier or a slip
    persist: int = 2  # consecutive outliers that mean the anchor moved

    def measurement_sigma_mm(self, peak_mm: float) -> float:
        """Per-axis standard deviation of one window's dent core with the map's peak ``peak_mm``."""
        return max(self.noise_mm2 / max(peak_mm, 1e-6), self.floor_mm)


class AnchorFilter:
    """One contact's anchor over the windows of a run; :meth:`update` per window, in order."""

    def __init__(self, params: AnchorParams | None = None) -> None:
        self.params = params or AnchorParams()
        self.anchor_mm: Array | None = None  # (2,) gel frame x, y at rest; None out of contact
        self.variance_mm2 = 0.0  # per axis (the filter is isotropic)
        self.outliers = 0  # consecutive cores outside the gate

    def reset(self) -> None:
        self.anchor_mm, self.variance_mm2, self.outliers = None, 0.0, 0

    def update(self, core_mm: npt.ArrayLike | None, peak_mm: float, dt_s: float) -> Array | None:
        """The anchor (2,) mm after a window whose dent core is ``core_mm`` (None: no dent, the contact
        ended) with the map's peak depth ``peak_mm``, ``dt_s`` after the previous window."""
        if core_mm is None:
            self.reset()
            return None
        p = self.params
        z = np.asarray(core_mm, np.float64)
        noise = p.measurement_sigma_mm(peak_mm) ** 2
        if self.anchor_mm is None:
            self.anchor_mm, self.variance_mm2, self.outliers = z.copy(), noise, 0
            return self.anchor_mm.copy()
        self.variance_mm2 += p.slip_diffusion_mm2_s * max(dt_s, 0.0)
        innovation = z - self.anchor_mm
        distance2 = float(innovation @ innovation)
        spread = self.variance_mm2 + noise
        if distance2 / spread > p.gate:
            if noise < self.variance_mm2:  # a surer core than the anchor, far from it: a new contact
                self.anchor_mm, self.variance_mm2, self.outliers = z.copy(), noise, 0
                return self.anchor_mm.copy()
            self.outliers += 1
            if self.outliers >= p.persist:  # the contact slipped: follow it
                self.variance_mm2 += distance2 / 2.0
                spread = self.variance_mm2 + noise
            else:  # one improbable core: bound its pull
                spread *= distance2 / spread / p.gate
        else:
            self.outliers = 0
        gain = self.variance_mm2 / spread
        self.anchor_mm = self.anchor_mm + gain * innovation
        self.variance_mm2 *= 1.0 - gain
        return self.anchor_mm.copy()


def anchor_px(anchor_mm: npt.ArrayLike, camera: CameraModel) -> Array:
    """The anchor (2,) mm on the gel's rest surface (z = 0) in sensor pixels (x, y)."""
    x, y = np.asarray(anchor_mm, np.float64)
    return np.asarray(camera.project(np.array([[x, y, 0.0]])), np.float64)[0]
