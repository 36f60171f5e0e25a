"""Probing runs through the real drivers over ptys on the virtual rig: a full run, then each safety stop."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.indenters import Indenter
from labrig.physics.geometry import nominal_gel_in_machine
from labrig.protocol.rigfile import DeviceConfig
from labrig.protocol.runner import ProbeRunner, RunResult
from labrig.protocol.safety import SafetyError, SafetyLimits, StopRequest
from labrig.protocol.session import RigSession
from labrig.protocol.spec import ApproachSpec, ProbeSpec
from labrig.recording import Recording
from labrig.sim.world import LiveWorld

QUICK = ProbeSpec(
    "sphere", depth_mm=0.8, normal_speed_mm_s=2.0, wait_s=0.15, shear_mm=0.5, shear_speed_mm_s=2.0,
    approach=ApproachSpec(start_height_mm=0.4, speed_mm_s=1.0, contact_force_n=0.1, max_travel_mm=1.5),
    retract_height_mm=1.0, retract_speed_mm_s=5.0,
)


def _runner(session: RigSession, rig: RigConfig, sphere: Indenter, stop: StopRequest | None = None) -> ProbeRunner:
    return ProbeRunner(session, rig, sphere, gel_in_machine=nominal_gel_in_machine(rig), stop=stop)


def test_a_full_run_on_the_virtual_rig_records_everything(rig: RigConfig, sphere: Indenter, tmp_path: Path) -> None:
    """The default path: the virtual rig in its own process, drivers over ptys and the camera socket."""
    with RigSession(rig, DeviceConfig(), SafetyLimits(), indenter=sphere) as session:
        result = _runner(session, rig, sphere).run(QUICK, tmp_path / "run.h5")
    assert result.exit_status == "complete", result.reason
    assert result.phases == list(QUICK.phases())
    with Recording(result.path) as rec:
        assert rec.exit_status == "complete"
        assert [p.name for p in rec.phases()] == list(QUICK.phases())
        assert rec.rows("events") > 10_000 and rec.rows("ft") > 1000 and rec.rows("cnc") > 10
        assert rec.rows("triggers") == rec.rows("trigger_out") == len(QUICK.phases())
        assert rec.rows("truth/contact") > 10 and rec.rows("truth/depth") > 10
        fz = rec.column("ft", "force_n")[:, 2]
        truth_fz = -rec.column("truth/contact", "force_n")[:, 2]
        assert fz.max() == pytest.approx(truth_fz.max(), rel=0.05)  # the sensor saw the rig's force
        assert rec.clock_model("camera").method.startswith("triggers")


def test_waits_add_trigger_edge_pairs_for_the_clock_fit(rig: RigConfig, sphere: Indenter, tmp_path: Path) -> None:
    """A wait long enough for sync pulses toggles the trigger in pairs: every phase keeps its edge
    and level, the camera sees every edge, and the clock fit rests on them."""
    spec = replace(QUICK, wait_s=0.8)  # one pair per wait (SYNC_EDGE_INTERVAL_S = 0.25 s)
    with RigSession(rig, DeviceConfig(), SafetyLimits(), indenter=sphere) as session:
        result = _runner(session, rig, sphere).run(spec, tmp_path / "run.h5")
    assert result.exit_status == "complete", result.reason
    waits = list(spec.phases()).count("wait")
    with Recording(result.path) as rec:
        assert [p.name for p in rec.phases()] == list(spec.phases())
        n_edges = len(spec.phases()) + 2 * waits
        assert rec.rows("triggers") == rec.rows("trigger_out") == n_edges
        sent = rec.column("trigger_out", "t_host_us")
        polarity = rec.column("trigger_out", "polarity")
        starts = np.array([p.t_start_us for p in rec.phases()])
        at_phase = np.isin(sent, starts)
        assert at_phase.sum() == len(spec.phases())
        assert polarity[at_phase].tolist() == [(k + 1) % 2 for k in range(len(spec.phases()))]
        camera = rec.clock_model("camera")
        # the line through the pairs ("triggers"), or on a host so loaded that the pairs agree on no line, the
        # envelope's drift with the offset from the pairs ("envelope+trigger"): both rest on every edge
        assert camera.method in ("triggers", "envelope+trigger") and camera.n_trigger_pairs == n_edges
        assert (rec.column("trigger_out", "t_latest_host_us") > sent).all() and np.isfinite(camera.offset_bound_us)


@pytest.fixture()
def live(rig: RigConfig, sphere: Indenter, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[LiveWorld, RigSession]]:
    """An in-process world, so tests can inject faults into its twins."""
    socket = tmp_path_factory.mktemp("sock") / "evk4.sock"
    with LiveWorld(rig, sphere, homed=True, camera_socket=socket) as world:
        with RigSession(rig, DeviceConfig(), SafetyLimits(), indenter=sphere, world=world) as session:
            yield world, session


def _soon(delay_s: float, action: Callable[[], None]) -> threading.Timer:
    timer = threading.Timer(delay_s, action)
    timer.start()
    return timer


def _when_phase(runner: ProbeRunner, phase: str, action: Callable[[], None], after_s: float = 0.05) -> threading.Thread:
    def watch() -> None:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            if runner._phases and runner._phases[-1] == phase:
                time.sleep(after_s)
                action()
                return
            time.sleep(0.005)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread


def _assert_retracted_and_saved(result: RunResult, session: RigSession, reason: str) -> None:
    assert result.exit_status == "aborted"
    assert reason in result.reason
    assert "retract failed" not in result.reason
    assert result.contact_mm is not None
    z = session.grbl.status().position_mm[2]  # type: ignore[union-attr]
    assert z > result.contact_mm[2] + 0.5  # out of the gel
    with Recording(result.path) as rec:
        assert rec.exit_status == "aborted" and reason in rec.exit_reason
        assert rec.rows("ft") > 100
        assert rec.phases()[-1].name == "retract"


def test_bad_targets_are_refused_before_any_move(rig: RigConfig, sphere: Indenter, live, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    _, session = live
    runner = _runner(session, rig, sphere)
    before = session.grbl.status().position_mm  # type: ignore[union-attr]
    with pytest.raises(SafetyError, match="edge"):
        runner.run(replace(QUICK, location_mm=(14.0, 0.0)), tmp_path / "a.h5")
    with pytest.raises(SafetyError, match="max_depth_mm"):
        runner.run(replace(QUICK, depth_mm=3.0), tmp_path / "b.h5")
    session.limits = replace(session.limits, workspace_min_mm=(-200.0, -200.0, -45.0))
    cramped = _runner(session, rig, sphere)
    with pytest.raises(SafetyError, match="outside the workspace"):
        cramped.run(QUICK, tmp_path / "c.h5")
    assert session.grbl.status().position_mm == before  # type: ignore[union-attr]
    assert not list(tmp_path.iterdir())  # nothing recorded


def test_a_force_over_the_limit_mid_shear_holds_and_retracts(rig: RigConfig, sphere: Indenter, live, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    _, session = live
    session.limits = replace(session.limits, max_shear_force_n=0.6)
    session.monitor.limits = session.limits
    result = _runner(session, rig, sphere).run(QUICK, tmp_path / "trip.h5")
    _assert_retracted_and_saved(result, session, "force limit")
    assert "shear force" in result.reason
    assert "shear" in result.phases and "normal_up" not in result.phases


def test_a_grbl_alarm_mid_run_stops_and_retracts(rig: RigConfig, sphere: Indenter, live, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    world, session = live
    runner = _runner(session, rig, sphere)
    _when_phase(runner, "normal_down", lambda: world.grbl.trip_hard_limit(world.server.now_us()))
    result = runner.run(QUICK, tmp_path / "alarm.h5")
    _assert_retracted_and_saved(result, session, "GRBL")


def test_losing_the_ft_sensor_stops_and_retracts(rig: RigConfig, sphere: Indenter, live, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    world, session = live
    runner = _runner(session, rig, sphere)
    _when_phase(runner, "wait", lambda: world.server.unplug("bota"))
    result = runner.run(QUICK, tmp_path / "ft.h5")
    _assert_retracted_and_saved(result, session, "F/T sensor lost")


def test_a_broken_camera_stream_stops_and_retracts(rig: RigConfig, sphere: Indenter, live, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """A failure in the camera's reader thread aborts the run with its reason (never a silently short recording)."""
    _, session = live
    runner = _runner(session, rig, sphere)

    def broken(data: bytes) -> None:
        raise RuntimeError("USB transfer error")

    _when_phase(runner, "wait", lambda: setattr(session.camera._decoder, "feed", broken))  # type: ignore[union-attr]
    result = runner.run(QUICK, tmp_path / "cam.h5")
    _assert_retracted_and_saved(result, session, "camera lost")
    assert "USB transfer error" in result.reason


def test_ctrl_c_twice_holds_and_retracts_at_once(rig: RigConfig, sphere: Indenter, live, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    _, session = live
    stop = StopRequest()
    runner = _runner(session, rig, sphere, stop)
    _when_phase(runner, "shear", lambda: (stop.request(), stop.request()))
    result = runner.run(replace(QUICK, shear_speed_mm_s=0.5), tmp_path / "twice.h5")
    _assert_retracted_and_saved(result, session, "second Ctrl-C")
    assert "shear_opposite" not in result.phases


def test_ctrl_c_once_finishes_the_phase_then_stops(rig: RigConfig, sphere: Indenter, live, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    _, session = live
    stop = StopRequest()
    runner = _runner(session, rig, sphere, stop)
    _when_phase(runner, "normal_down", stop.request)
    result = runner.run(QUICK, tmp_path / "once.h5")
    _assert_retracted_and_saved(result, session, "stopped by the user")
    assert result.phases == ["approach", "normal_down", "retract"]  # normal_down ran to its end first
    with Recording(result.path) as rec:
        depth = rec.column("cnc", "position_mm")[:, 2].min()
    assert depth == pytest.approx(result.contact_mm[2] - QUICK.depth_mm, abs=0.05)  # type: ignore[index]
    assert np.isfinite(depth)


def test_a_press_beyond_the_gel_model_aborts_the_run_and_the_rig_stays_up(rig: RigConfig, sphere: Indenter,
                                                                          tmp_path: Path) -> None:
    """The rig's gel model ends at 0.8 mm while the runner's indenter allows 2.5 mm: the press goes
    beyond the model. The run aborts with a clear reason and retracts; the twins keep serving and
    the next run on the same rig completes."""
    shallow_model = replace(sphere, max_depth_mm=0.8)
    with LiveWorld(rig, shallow_model, homed=True, camera_socket=tmp_path / "evk4.sock") as world:
        with RigSession(rig, DeviceConfig(), SafetyLimits(), indenter=sphere, world=world) as session:
            runner = _runner(session, rig, sphere)
            deep = runner.run(replace(QUICK, depth_mm=0.95, shear_mm=0.0), tmp_path / "deep.h5")
            assert deep.exit_status == "aborted"
            assert "refused a request" in deep.reason and "beyond the gel model" in deep.reason
            assert "retract failed" not in deep.reason, deep.reason[-600:]
            assert world.error is None and world.server.error is None
            again = runner.run(replace(QUICK, depth_mm=0.3), tmp_path / "again.h5")
            assert again.exit_status == "complete", again.reason
    with Recording(again.path) as rec:  # it carries its indenter's definition
        assert rec.attrs["indenter_definition"].startswith("[sphere]\nkind = \"sphere\"")


def test_a_twin_starved_for_seconds_answers_late_and_the_run_completes(rig: RigConfig, sphere: Indenter,
                                                                        tmp_path: Path) -> None:
    """Starvation without load: the virtual rig's process is stopped (SIGSTOP) for 4 s mid-run, so the
    GRBL twin answers a line and its status queries seconds late. The run waits and completes. The F/T
    twin catches up with 4 s of frames at once (118 KB): the pty and the port's host buffer hold 83 KB
    of them, the rest (about 1.2 s) are lost, as from a real port nobody read for that long."""
    import os
    import signal

    with RigSession(rig, DeviceConfig(), SafetyLimits(), indenter=sphere) as session:
        runner = _runner(session, rig, sphere)
        pid = session.world._process.pid  # type: ignore[union-attr]

        def starve() -> None:
            os.kill(pid, signal.SIGSTOP)
            time.sleep(4.0)
            os.kill(pid, signal.SIGCONT)

        _when_phase(runner, "wait", starve)
        result = runner.run(QUICK, tmp_path / "starved.h5")
    assert result.exit_status == "complete", result.reason
    # ... but short of F/T data while the twin was stopped: marked, never silently kept.
    assert result.shortfall.fell_behind and 0.5 < result.shortfall.ft_max_gap_s < 3.0
    with Recording(result.path) as rec:
        assert "F/T frames missing" in rec.attrs["fell_behind"] and 0.5 < rec.attrs["ft_max_gap_s"] < 3.0


def test_a_held_shear_through_the_drivers_reaches_and_holds_its_force(rig: RigConfig, sphere: Indenter,
                                                                     tmp_path: Path) -> None:
    """Pressed 0.8 mm (about 4.5 N), sheared 1 mm holding 2 N: absolute jog segments every 10 ms on the host clock
    bring the F/T's |Fz| to the target during the shear and hold it through the shear back."""
    spec = replace(QUICK, shear_hold_force_n=2.0, shear_mm=1.0, shear_speed_mm_s=1.0)
    with RigSession(rig, DeviceConfig(), SafetyLimits(), indenter=sphere) as session:
        result = _runner(session, rig, sphere).run(spec, tmp_path / "held.h5")
    assert result.exit_status == "complete", result.reason
    with Recording(result.path) as rec:
        t = rec.column("ft", "t_host_us")
        fz = np.abs(rec.column("ft", "force_n")[:, 2] - rec.column("ft", "force_n")[:100, 2].mean())
        back = next(p for p in rec.phases() if p.name == "shear_opposite")
        during = fz[(t >= back.t_start_us) & (t < back.t_end_us)]
        assert np.sqrt(np.mean((during - 2.0) ** 2)) < 0.15
        control = rec.stream("control")
        assert len(control["t_host_us"]) >= 150 and np.median(control["reading_age_us"]) < 5_000
