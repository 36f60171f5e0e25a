"""Calibration from recordings: camera intrinsics, gel-to-camera extrinsics, rig registration, gel modulus.

Fits and files only; nothing here moves the rig. Camera: :mod:`.eventframes`
(events to frames over blink periods), :mod:`.intrinsics`, :mod:`.extrinsics`
and :mod:`.files` (TOML outputs and their loaders). Rig: :mod:`.registration`
(the registration from touch-offs), :mod:`.contact_location`, :mod:`.fits`,
:mod:`.registration_file`; :mod:`.gel` (the modulus fit and ``gel.toml``);
:mod:`.plots`. The procedures that record the inputs on the rig are in
:mod:`labrig.protocol.touchoff` and :mod:`labrig.protocol.calibration_runs`; the
scenes recorded on the virtual rig in :mod:`labrig.sim.calibration_scenes`.
"""
