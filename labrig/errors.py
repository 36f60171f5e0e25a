"""User-facing errors: each says what is wrong and what to do, in one line.

The CLI prints a :class:`LabrigError` without a traceback and exits with code 2;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class LabrigError(Exception):
    """A problem the user can fix; the message says how."""

    exit_code = 2


class ConfigError(LabrigError):
    """A bad rig configuration file."""


class SomeInputsFailed(LabrigError):
    """A command failed on some of its inputs and kept what the others gave; the message says how many.

    Exit code 1: the command ran, its inputs were not all usable (2 is for a bad command line)."""

    exit_code = 1


class ModelCardError(LabrigError):
    """A depth network's model card (``NAME.json`` beside ``NAME.onnx``) that cannot be used."""


class RecordingError(LabrigError):
    """A recording file cannot be opened or used."""


class RecordingFault(LabrigError):
    """Recording stopped early (disk full, write failure); recorded data was kept."""


class CalibrationError(LabrigError):
    """Calibration cannot proceed from this input; the message says what was found and what to change."""
