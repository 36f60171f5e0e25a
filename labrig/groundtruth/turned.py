"""A contact model of a non-axisymmetric indenter turned relative to the gel.

The ground truth's contact models (:mod:`labrig.groundtruth.contact`) describe
the indenter in its own frame. An indenter turned by ``yaw_deg`` about the
gel's z axis relative to the gel (its ``yaw_deg`` in the CNC frame minus the
gel's yaw in the machine, as the lab knows it: the rig registration or the
nominal pose) presses the same field turned: :class:`TurnedModel` turns the
query points (gel frame, relative to the contact centre) into the indenter
frame, so the labels follow the footprint exactly as the virtual rig's contact
tables do (:func:`~labrig.sim.truth_config.true_contact_table`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.calibration.fits import yaw_tilt_of
from labrig.frames import Pose
from labrig.groundtruth.contact import ContactModel
from labrig.indenters import Indenter

F64 = npt.NDArray[np.float64]


class TurnedModel:
    """``model`` (indenter frame) seen from the gel frame, the indenter turned by ``yaw_deg`` (deg, about +z)."""

    def __init__(self, model: ContactModel, yaw_deg: float) -> None:
        self.model = model
        self.yaw_deg = float(yaw_deg)
        self.elastic = model.elastic
        self.method = model.method
        c, s = np.cos(np.radians(self.yaw_deg)), np.sin(np.radians(self.yaw_deg))
        self._to_indenter = np.array([[c, s], [-s, c]])

    def fields(self, delta_mm: float, dx_mm: F64, dy_mm: F64) -> tuple[F64, npt.NDArray[np.bool_]]:
        """(uz mm, contact mask) at gel-frame points (dx, dy) relative to the contact centre."""
        (a, b), (c, d) = self._to_indenter
        dx, dy = np.asarray(dx_mm, np.float64), np.asarray(dy_mm, np.float64)
        return self.model.fields(delta_mm, a * dx + b * dy, c * dx + d * dy)

    def force_n(self, delta_mm: float) -> float:
        return self.model.force_n(delta_mm)

    def slip_shift_mm(self, delta_mm: float, direction: F64 | None = None) -> float:
        """The gross-slip shift along a gel-frame ``direction`` (turned into the indenter frame)."""
        turned = None if direction is None else self._to_indenter @ np.asarray(direction, np.float64)
        return self.model.slip_shift_mm(delta_mm, turned)

    def describe(self) -> dict[str, Any]:
        return {**self.model.describe(), "footprint_yaw_deg": self.yaw_deg}


def lab_footprint_yaw_deg(indenter: Indenter, gel_in_machine: Pose) -> float:
    """The indenter's turn relative to the gel as the lab knows it: its ``yaw_deg`` minus the gel pose's
    yaw (deg), reduced by its symmetry; 0 for axisymmetric indenters."""
    gel_yaw_deg, _ = yaw_tilt_of(gel_in_machine.rotation)
    return indenter.footprint_yaw_deg(gel_yaw_deg)


def turned_model(model: ContactModel, indenter: Indenter, gel_in_machine: Pose) -> ContactModel:
    """``model`` turned by the indenter's footprint yaw relative to the gel (itself when that is 0)."""
    yaw = lab_footprint_yaw_deg(indenter, gel_in_machine)
    return model if yaw == 0.0 else TurnedModel(model, yaw)
