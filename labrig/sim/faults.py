"""Requests the virtual rig refused while it kept running.

A twin must never die on a request: what its model cannot serve (a press beyond the gel
model's depth, a twin that raises) is kept as a :class:`RigFault`, the rig goes on serving,
and its owner (the world process, a probing run) reports it; a run that sees one that
happened during it aborts with its message and retracts.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RigFault:
    """One refused request: when (host us, the rig's clock) and what."""

    t_host_us: int
    message: str

    def __str__(self) -> str:
        return self.message
