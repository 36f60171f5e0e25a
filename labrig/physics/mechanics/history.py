"""Shear loading history by Masing superposition of monotonic solutions.

At constant normal load, a Cattaneo-Mindlin contact unloaded from a shift s_r
follows (Mindlin & Deresiewicz 1953; Jager's and Ciavarella's superposition):

    F(s) = F(s_r) + 2 F_mono((s - s_r) / 2)

for every tangential field F (traction, in-plane surface displacement, force),
with F_mono the monotonic solution from zero, which is odd in the shift
(F_mono(-x) = -F_mono(x)). After the first reversal from s_max:
F(s) = F_mono(s_max) - 2 F_mono((s_max - s) / 2); at s = -s_max the loop
closes at -F_mono(s_max). Further reversals nest the same rule, and a branch
that passes the reversal point it started from rejoins the older branch
(Masing's memory rule; the first branch rejoins the virgin curve at -s_max).

The superposition is exact for the half-space Cattaneo-Mindlin problem when
the tangential kernel is proportional to the normal one; here it is an
approximation (the disc-constrained traction can then exceed mu p slightly,
so :class:`~labrig.physics.mechanics.tables.ContactTable` clips it). It assumes a constant depth while shearing: if the depth
changes, the terms are evaluated at the current depth.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import pairwise

Term = tuple[float, float]  # (weight, monotonic shift in mm)


@dataclass
class ShearHistory:
    """Masing memory of a 1-D shear path (signed shift along one axis, mm).

    Feed it every shift in order with :meth:`advance`; it returns the terms
    ((w_j, s_j), ...) such that F(s) = sum_j w_j F_mono(s_j). ``axis`` (a unit
    2-vector in the gel frame) is fixed by the first non-zero vector shift a
    table sees; scalar shifts are along the table's own direction.
    """

    reversals_mm: list[float] = field(default_factory=list)
    last_mm: float = 0.0
    direction: int = 0  # +1 increasing, -1 decreasing, 0 not moved yet
    axis: tuple[float, float] | None = None

    def advance(self, shift_mm: float) -> tuple[Term, ...]:
        """Move to ``shift_mm`` and return the superposition terms for it."""
        s = float(shift_mm)
        step = s - self.last_mm
        moving = (step > 0) - (step < 0)
        if moving and self.direction and moving != self.direction:
            self.reversals_mm.append(self.last_mm)
        if moving:
            self.direction = moving
        self.last_mm = s
        self._forget_passed_reversals(s)
        return self.terms(s)

    def terms(self, shift_mm: float) -> tuple[Term, ...]:
        """Terms of the current branch at ``shift_mm`` (does not change the state)."""
        r = self.reversals_mm
        if not r:
            return ((1.0, shift_mm),)
        out = [(1.0, r[0])]
        out += [(2.0, (b - a) / 2) for a, b in pairwise(r)]
        out.append((2.0, (shift_mm - r[-1]) / 2))
        return tuple(out)

    def reset(self) -> None:
        """Back to the unloaded, virgin state (e.g. after lifting off)."""
        self.reversals_mm.clear()
        self.last_mm, self.direction, self.axis = 0.0, 0, None

    def _forget_passed_reversals(self, s: float) -> None:
        r = self.reversals_mm
        while r:
            start = r[-1]
            previous = r[-2] if len(r) >= 2 else -r[-1]  # the virgin branch "starts" at -s_max
            if (s - start) * (previous - start) > 0 and abs(s - start) >= abs(previous - start):
                del r[-2:]  # both turning points are wiped out (only one on the first branch)
            else:
                break
