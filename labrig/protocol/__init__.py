"""Probing protocols and campaigns: the run as data (spec), its files, the dataset split;
and the runner that drives the rig through it."""

from labrig.protocol.files import apply_overrides, load_campaign, load_protocol
from labrig.protocol.spec import ApproachSpec, Campaign, ProbeSpec, ProtocolError, RecordingPlan

__all__ = [
    "ApproachSpec",
    "Campaign",
    "ProbeSpec",
    "ProtocolError",
    "RecordingPlan",
    "apply_overrides",
    "load_campaign",
    "load_protocol",
]
