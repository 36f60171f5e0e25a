"""A campaign's sensor variation: each virtual recording on a sensor of its own, as real sensors vary.

A campaign file's ``[vary]`` section names virtual-rig keys (``sim.*``, as
:func:`labrig.config.rig_with` takes them) and the range each is drawn from per recording::

    [vary]
    "sim.events.shot_noise_rate_hz" = [0.05, 2.0]     # uniform in [low, high]
    "sim.markers.position_error_mm" = [0.0, 0.08]
    "sim.markers.missing_count" = [0, 3]              # whole numbers: uniform over low..high
    "sim.markers.seed" = "recording"                  # the recording's own seed
    "sim.grbl.max_rate_mm_min" = [3600, 3600]         # low = high: that value for every recording

A recording's values come from its own seed (the campaign's seed and its index), so the same
campaign gives the same sensors wherever it runs; the recording stores the rig text with the
drawn values. Only the virtual rig's truth (``sim.*``) varies: what the lab knows of its sensor
(``[gel]``, ``[camera]``, ...) comes from calibration and stays as the rig file says. A
campaign's speeds are checked against the slowest virtual CNC its ``sim.grbl`` keys give
(:func:`slowest_machine`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from labrig.config import RigConfig, TomlValue, rig_with
from labrig.errors import ConfigError
from labrig.sim.truth_config import sim_config

#: The value of a key that takes the recording's own seed (e.g. the marker printing's).
RECORDING_SEED = "recording"


@dataclass(frozen=True)
class VariedKey:
    """One varied rig key: uniform in [low, high] (whole numbers when ``integer``), or the recording's seed."""

    key: str
    low: float = 0.0
    high: float = 0.0
    integer: bool = False
    recording_seed: bool = False


@dataclass(frozen=True)
class SensorVariation:
    """The ``[vary]`` section of a campaign: the keys drawn per recording."""

    keys: tuple[VariedKey, ...]

    def draw(self, seed: int) -> dict[str, TomlValue]:
        """The values of one recording whose seed is ``seed`` (the same seed, the same values)."""
        rng = np.random.default_rng([seed, 0x5E5])
        values: dict[str, TomlValue] = {}
        for k in self.keys:  # one draw per key, in file order, whatever its kind
            u = float(rng.random())
            if k.recording_seed:
                values[k.key] = int(seed)
            elif k.integer:
                values[k.key] = int(k.low + min(int(u * (k.high - k.low + 1)), int(k.high - k.low)))
            else:
                values[k.key] = float(k.low + u * (k.high - k.low))
        return values

    def varies(self, prefix: str) -> bool:
        """Whether some varied key starts with ``prefix`` (e.g. ``sim.events.threshold``)."""
        return any(k.key.startswith(prefix) for k in self.keys)

    def rig_for(self, rig: RigConfig, seed: int) -> RigConfig:
        """``rig`` with the values of the recording whose seed is ``seed``."""
        return rig_with(rig, self.draw(seed))


def parse_variation(table: Mapping[str, object], rig: RigConfig | None) -> tuple[SensorVariation, list[tuple[str, str]]]:
    """The ``[vary]`` table checked: the variation and a list of (key, problem) for the ones refused.

    With a ``rig``, each key is tried at both ends of its range, so a key the rig cannot take or a
    value it refuses is reported here, before any recording."""
    keys: list[VariedKey] = []
    problems: list[tuple[str, str]] = []
    for key, value in table.items():
        if not key.startswith("sim."):
            problems.append((key, "only the virtual rig's truth varies: give a sim.* key (what the lab knows of its "
                                  "sensor comes from calibration)"))
            continue
        if value == RECORDING_SEED:
            keys.append(VariedKey(key, recording_seed=True))
            continue
        if (not isinstance(value, list) or len(value) != 2
                or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)):
            problems.append((key, f'give a range [low, high] or "{RECORDING_SEED}", not {value!r}'))
            continue
        low, high = value
        if high < low:
            problems.append((key, f"the range [{low}, {high}] is reversed; give [low, high]"))
            continue
        varied = VariedKey(key, float(low), float(high), integer=isinstance(low, int) and isinstance(high, int))
        if rig is not None:
            try:
                for end in (low, high):
                    sim_config(rig_with(rig, {key: int(end) if varied.integer else float(end)}))
            except ConfigError as exc:
                problems.append((key, str(exc)))
                continue
        keys.append(varied)
    return SensorVariation(tuple(keys)), problems


def slowest_machine(rig: RigConfig, variation: SensorVariation) -> RigConfig:
    """``rig`` with every varied ``sim.grbl`` key at the low end of its range: the slowest virtual
    CNC any recording of the campaign gets (the campaign's speeds are checked against it)."""
    low: dict[str, TomlValue] = {k.key: int(k.low) if k.integer else k.low for k in variation.keys
                                 if k.key.startswith("sim.grbl.") and not k.recording_seed}
    return rig_with(rig, low) if low else rig
