"""The force loop on the event sensor's estimate: the pipeline beside a run in virtual time feeds the loop, which
holds the estimate; the F/T sensor, the reference, shows how close the estimate is; a camera that stops stalls the
loop, which stops and retracts."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.evaluation.control import control_run
from labrig.indenters import Indenter
from labrig.protocol.event_estimate import EventEstimator
from labrig.protocol.feedback import EVENTS_LOOP_DEFAULTS, EVENTS_STALE_AFTER_S, Estimate, EstimateFeedback
from labrig.protocol.force_loop import ForceLoopParams
from labrig.protocol.spec import ApproachSpec, ProbeSpec
from labrig.protocol.virtual_run import record_virtual
from labrig.recording import Recording

HELD = ProbeSpec(
    "sphere", force_n=3.0, press_hold_s=0.8, wait_s=0.3, shear_mm=0.0, normal_speed_mm_s=2.0, feedback="events",
    control=ForceLoopParams(**EVENTS_LOOP_DEFAULTS),
    approach=ApproachSpec(start_height_mm=0.4, speed_mm_s=1.0, contact_force_n=0.1, max_travel_mm=1.5),
    retract_height_mm=1.0,
)


def test_the_estimate_is_read_as_a_normal_force_pressing_positive_at_its_window_end() -> None:
    feedback = EstimateFeedback()
    assert feedback.normal_reading() == (0.0, None)
    feedback.publish(Estimate(123_000, np.array([0.1, -0.2, -2.5]), np.zeros((156, 3))))
    assert feedback.normal_reading() == (2.5, 123_000) and feedback.windows == 1


def test_a_held_press_on_the_event_estimate_holds_the_estimate(rig: RigConfig, sphere: Indenter,
                                                               tmp_path: Path) -> None:
    """The loop reads the pipeline's estimate, 10-150 ms after its window's end; it holds that estimate at 3 N
    through the press's hold and the wait, and the F/T sensor (never read by the loop) agrees within 15 %."""
    result = record_virtual(HELD, tmp_path / "events.h5", rig, sphere, seed=3)
    assert result.exit_status == "complete", result.reason
    with Recording(result.path) as rec:
        assert rec.attrs["extra_control_feedback"] == "events"
        assert rec.attrs["extra_control_reading_noise_n"] == EVENTS_LOOP_DEFAULTS["reading_noise_n"]
        control = rec.stream("control")
        t_ft = rec.column("ft", "t_host_us")
        fz = np.abs(rec.column("ft", "force_n")[:, 2] - rec.column("ft", "force_n")[:100, 2].mean())
        wait = next(p for p in rec.phases() if p.name == "wait")
    age_ms = control["reading_age_us"] / 1e3
    assert 10 < np.median(age_ms) < EVENTS_STALE_AFTER_S * 1e3
    held = (control["t_host_us"] >= wait.t_start_us) & (control["t_host_us"] < wait.t_end_us)
    assert np.abs(control["feedback_n"][held] - 3.0).max() < 0.3  # the loop holds what it reads
    ft_at = np.interp(control["t_host_us"][held], t_ft, fz)
    assert not np.allclose(ft_at, control["feedback_n"][held], atol=1e-3)  # it read the estimate, not the F/T
    assert abs(ft_at.mean() - 3.0) < 0.45
    run = control_run(result.path)  # labrig evaluate's control section: the F/T against the target
    assert run is not None and run.feedback == "events" and run.hold_rms_n_ft < 0.6
    # the estimate's scatter about its own error: far above the F/T's (0.02 N), within what the loop is told
    assert 0.03 < run.reading_scatter_n < EVENTS_LOOP_DEFAULTS["reading_noise_n"]


def test_a_camera_that_stops_stalls_the_loop_which_stops_and_retracts(rig: RigConfig, sphere: Indenter,
                                                                      tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """The camera's chunks stop reaching the pipeline 0.3 s into the press: the newest estimate ages past
    stale_after_s, the loop stops within one segment after that and the run retracts."""
    delivered = EventEstimator.on_chunk
    cut: dict[str, int] = {}

    def lost_after_contact(self: EventEstimator, chunk: object) -> None:
        newest = self.feedback.newest
        if newest is not None and -newest.net_force_n[2] > 0.5:
            cut.setdefault("t_ns", newest.t_host_ns)
            return  # the camera is lost once the press is under way
        delivered(self, chunk)  # type: ignore[arg-type]

    monkeypatch.setattr(EventEstimator, "on_chunk", lost_after_contact)
    spec = replace(HELD, control=ForceLoopParams(stale_after_s=0.05))
    result = record_virtual(spec, tmp_path / "stalled.h5", rig, sphere, seed=3)
    assert result.exit_status == "aborted"
    assert "the force feedback stalled: the newest reading is" in result.reason
    assert result.phases[-1] == "retract" and "wait" not in result.phases
    with Recording(result.path) as rec:
        age_us = rec.column("control", "reading_age_us")
    assert "t_ns" in cut
    # the last segment was commanded on a reading still fresh; the next update found it stale and stopped
    segment_us = spec.control.segment_s * 1e6
    assert 50_000 - 2 * segment_us < age_us[-1] <= 50_000


def test_recording_a_loop_on_the_event_sensor_without_the_live_pipeline_says_how(tmp_path: Path) -> None:
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-m", "labrig.cli", "record", "--protocol",
                           str(root / "protocols" / "held-press-events.toml"), "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=60, cwd=root)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "labrig run --live --protocol FILE" in done.stderr and not any(tmp_path.iterdir())
