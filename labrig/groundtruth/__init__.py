"""Ground-truth normal-deformation maps and contact masks for recordings (``labrig groundtruth``).

Computed from what a real lab has -- the CNC pose stream, the indenter
geometry, the gel modulus, the rig registration and the camera calibration --
never from a simulated recording's ``/truth`` streams. Written to a sidecar
``NAME.gt.h5`` beside each recording (:func:`labrig.dataset.sidecar_path`). See docs/groundtruth.md.

* :mod:`contact` -- contact models: Hertz, Sneddon's integrals, the tabulated
  numerical solver (half-space or bonded layer).
* :mod:`inputs` -- the lab's knowledge (calibration files or nominal values).
* :mod:`generate` -- pose, indentation, maps on the network grid.
* :mod:`turned` -- a non-axisymmetric indenter's field turned by its yaw relative to the gel.
* :mod:`sidecar` -- the file and its reader (:func:`load_groundtruth`).
* :mod:`batch` -- whether a sidecar is current; a plot of a few maps.
"""

from labrig.groundtruth.contact import (
    CONTACT_METHODS,
    ELASTIC_MODELS,
    DepthTable,
    HertzModel,
    SneddonModel,
    choose_model,
)
from labrig.groundtruth.generate import DEFAULT_SCALE_MM, GroundTruth, generate
from labrig.groundtruth.inputs import GroundTruthError, LabInputs, lab_inputs
from labrig.groundtruth.sidecar import GroundTruthFile, load_groundtruth, write_sidecar

__all__ = [
    "CONTACT_METHODS",
    "DEFAULT_SCALE_MM",
    "ELASTIC_MODELS",
    "DepthTable",
    "GroundTruth",
    "GroundTruthError",
    "GroundTruthFile",
    "HertzModel",
    "LabInputs",
    "SneddonModel",
    "choose_model",
    "generate",
    "lab_inputs",
    "load_groundtruth",
    "write_sidecar",
]
