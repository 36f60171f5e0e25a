"""Between a campaign's runs: an Alarm left by an aborted run is cleared before the next run."""

from __future__ import annotations

from pathlib import Path

import pytest

from labrig.config import RigConfig
from labrig.errors import LabrigError
from labrig.indenters import Indenter
from labrig.physics.geometry import nominal_gel_in_machine
from labrig.protocol.rig_ready import grbl_in_alarm, ready_for_next_run
from labrig.protocol.rigfile import DeviceConfig
from labrig.protocol.runner import ProbeRunner
from labrig.protocol.safety import SafetyError, SafetyLimits
from labrig.protocol.session import RigSession
from labrig.protocol.spec import ApproachSpec, ProbeSpec
from labrig.sim.world import LiveWorld

QUICK = ProbeSpec(
    "sphere", depth_mm=0.6, normal_speed_mm_s=2.0, wait_s=0.1, shear_mm=0.0,
    approach=ApproachSpec(start_height_mm=0.4, speed_mm_s=1.0, contact_force_n=0.1, max_travel_mm=1.5),
    retract_height_mm=1.0, retract_speed_mm_s=5.0,
)


def test_an_alarm_left_between_runs_is_cleared_and_the_next_run_completes(rig: RigConfig, sphere: Indenter,
                                                                           tmp_path: Path) -> None:
    with LiveWorld(rig, sphere, homed=True, camera_socket=tmp_path / "evk4.sock") as world:
        with RigSession(rig, DeviceConfig(), SafetyLimits(), indenter=sphere, world=world) as session:
            runner = ProbeRunner(session, rig, sphere, gel_in_machine=nominal_gel_in_machine(rig))
            assert ready_for_next_run(session) == ""  # nothing to do
            world.grbl.trip_hard_limit(world.server.now_us())  # what an aborted run can leave behind
            assert grbl_in_alarm(session)
            session.devices = DeviceConfig()
            with pytest.raises(LabrigError, match="ALARM"):  # what every later run of the worker did before
                runner.run(QUICK, tmp_path / "refused.h5")
            done = ready_for_next_run(session)
            assert "unlocked" in done and not grbl_in_alarm(session)
            result = runner.run(QUICK, tmp_path / "next.h5")
            assert result.exit_status == "complete", result.reason

            world.grbl.trip_hard_limit(world.server.now_us())
            session.devices = DeviceConfig(grbl_port="/dev/null")  # as hardware without homing: nothing moves
            with pytest.raises(SafetyError, match=r"homing is off \(\$22=0\)"):
                ready_for_next_run(session)
            assert grbl_in_alarm(session)
            session.devices = DeviceConfig()
