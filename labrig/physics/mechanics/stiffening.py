"""Large-strain stiffening: a switchable, force-only non-linearity.

Real silicone stiffens at large strain, so a linear inverse model fitted at
small loads shows a force-dependent bias at high load. The virtual rig mimics
this with an effective modulus E_eff = E (1 + stiffening * strain), where

    strain = indentation depth / gel thickness

is the nominal compressive strain under the indenter tip (dimensionless; 0
above the surface). Under displacement control a linear-elastic solution
scales with E at fixed Poisson ratio, so this multiplies the pressure, the
tangential traction and every force by the same factor, and leaves all
displacement fields, the contact area and the stick zone unchanged.
``stiffening`` comes from rig.toml ``[sim.mechanics] stiffening``; 0 = linear.
"""

from __future__ import annotations


def stiffening_factor(indentation_mm: float, thickness_mm: float, stiffening: float) -> float:
    """1 + stiffening * max(indentation, 0) / thickness: the factor on pressures, tractions and forces."""
    if thickness_mm <= 0:
        raise ValueError(f"gel thickness must be positive, not {thickness_mm} mm")
    return 1.0 + float(stiffening) * max(float(indentation_mm), 0.0) / float(thickness_mm)
