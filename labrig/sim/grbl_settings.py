"""GRBL 1.1h settings (``$N``) as the twin's EEPROM holds them: defaults, types and the checks a write passes.

Units are GRBL's own: steps/mm (``$100-$102``), mm/min (``$110-$112``), mm/s**2 (``$120-$122``),
mm (``$130-$132``, ``$11``, ``$27``), us (``$0``), ms (``$1``, ``$26``).
"""

from __future__ import annotations

from collections.abc import Mapping

from labrig.devices.grbl_gcode import NUMBER
from labrig.devices.grbl_protocol import format_setting
from labrig.sim.imperfections import GRBL_MAX_STEP_RATE_HZ

#: The step rate GRBL's stepper interrupt can reach (a write that needs more is refused: error:12).
MAX_STEP_RATE_HZ = GRBL_MAX_STEP_RATE_HZ

#: GRBL 1.1h default settings ($$ of a fresh EEPROM).
DEFAULT_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
    20: 0, 21: 0, 22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0,
    100: 250.0, 101: 250.0, 102: 250.0, 110: 500.0, 111: 500.0, 112: 500.0,
    120: 10.0, 121: 10.0, 122: 10.0, 130: 200.0, 131: 200.0, 132: 200.0,
}  # fmt: skip
INTEGER_SETTINGS = frozenset({0, 1, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 30, 31, 32})
BOOLEAN_SETTINGS = frozenset({4, 13, 20, 21, 22, 32})


def initial_settings(overrides: Mapping[int, float] | None = None) -> dict[int, float]:
    """The 1.1h defaults with ``overrides`` on top; ValueError for a setting GRBL does not have."""
    settings: dict[int, float] = dict(DEFAULT_SETTINGS)
    for number, value in (overrides or {}).items():
        if number not in DEFAULT_SETTINGS:
            raise ValueError(f"GRBL has no setting ${number}")
        settings[number] = float(value)
    return settings


def setting_lines(settings: Mapping[int, float]) -> list[str]:
    """What ``$$`` prints, one line per setting in number order."""
    return [format_setting(n, settings[n], integer=n in INTEGER_SETTINGS) for n in sorted(settings)]


def write_setting(settings: dict[int, float], number: int, text: str) -> int | None:
    """``$N=text``: store it as GRBL would (integers truncated, booleans 0/1) and return None, or
    leave ``settings`` as they are and return GRBL's error code."""
    if NUMBER.fullmatch(text) is None:
        return 2
    value = float(text)
    if number not in DEFAULT_SETTINGS:
        return 3
    if value < 0:
        return 4
    if number in INTEGER_SETTINGS:
        value = float(int(value))
    if number in BOOLEAN_SETTINGS:
        value = 1.0 if value else 0.0
    if number == 0 and value < 3:
        return 6
    if number == 20 and value and not settings[22]:
        return 10
    if 100 <= number <= 102 and value * settings[number + 10] / 60.0 > MAX_STEP_RATE_HZ:
        return 12
    if 110 <= number <= 112 and settings[number - 10] * value / 60.0 > MAX_STEP_RATE_HZ:
        return 12
    settings[number] = value
    if number == 22 and not value:
        settings[20] = 0.0  # soft limits cannot stay on without homing
    return None
