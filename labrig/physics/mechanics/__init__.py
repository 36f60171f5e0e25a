"""Contact mechanics of a rigid indenter on the gel.

Shared by the virtual rig (forward solves and tables), ground truth (solves at the
measured tip), calibration (the modulus fit) and the inverse FEM (the layer compliance).

The gel is a layer (``GelConfig.thickness_mm``, E, nu) bonded to a rigid
window, or optionally an elastic half-space; Coulomb friction ``gel.friction``
with the indenter. Indenters are height maps (:mod:`labrig.indenters`).

Conventions in this package
---------------------------
* Gel frame axes x, y in the undeformed surface (z points out of the gel).
  Fields live on a local :class:`Grid` centred on the indenter tip.
* ``depth`` / ``uz``: normal surface displacement INTO the gel, positive when
  pressed (so a bulge is negative depth). Pressure positive in compression.
* Tractions and forces are what the indenter applies to the gel; normal
  force positive pressing. Units: mm, MPa, N (MPa mm^2 = N).

Pieces: :mod:`spectral` (Fourier compliances), :mod:`influence` (real-space
influence coefficients), :mod:`convolution` (DC-FFT), :mod:`kernels` (the
bundle per gel/grid/mode), :mod:`normal` (Polonsky-Keer), :mod:`tangential`
(Coulomb partial slip), :mod:`history` (Masing), :mod:`stiffening`,
:mod:`tables` (precomputed real-time lookups; built by :mod:`table_build`, cached by
:mod:`table_cache`), :mod:`rotation`.
"""

from labrig.physics.mechanics.grid import Grid
from labrig.physics.mechanics.history import ShearHistory
from labrig.physics.mechanics.kernels import Box, SurfaceKernels
from labrig.physics.mechanics.normal import NormalSolution, indenter_height_mm, solve_normal
from labrig.physics.mechanics.spectral import (
    confined_modulus_mpa,
    contact_modulus_mpa,
    halfspace_compliances,
    layer_longitudinal_compliance,
    layer_normal_compliance,
    layer_transverse_compliance,
    shear_modulus_mpa,
)
from labrig.physics.mechanics.stiffening import stiffening_factor
from labrig.physics.mechanics.table_cache import TABLE_VERSION, table_cache_dir
from labrig.physics.mechanics.tables import ContactFields, ContactTable
from labrig.physics.mechanics.tangential import TangentialSolution, full_slip_traction_mpa, solve_tangential

__all__ = [
    "TABLE_VERSION",
    "Box",
    "ContactFields",
    "ContactTable",
    "Grid",
    "NormalSolution",
    "ShearHistory",
    "SurfaceKernels",
    "TangentialSolution",
    "confined_modulus_mpa",
    "contact_modulus_mpa",
    "full_slip_traction_mpa",
    "halfspace_compliances",
    "indenter_height_mm",
    "layer_longitudinal_compliance",
    "layer_normal_compliance",
    "layer_transverse_compliance",
    "shear_modulus_mpa",
    "solve_normal",
    "solve_tangential",
    "stiffening_factor",
    "table_cache_dir",
]
