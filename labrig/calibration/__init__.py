"""Calibration from events: camera intrinsics, gel-to-camera extrinsics, rig registration, gel modulus.

Modules: :mod:`.scenes` (calibration scenes recorded on the virtual rig),
:mod:`.frames` (events to frames over blink periods), :mod:`.intrinsics`,
:mod:`.extrinsics` and :mod:`.files` (TOML outputs and their loaders).
Rig registration and the gel modulus live in their own modules.
"""
