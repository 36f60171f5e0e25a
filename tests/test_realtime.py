"""A through-driver run that fell behind real time is marked and retried, never kept silently short."""

from __future__ import annotations

from dataclasses import dataclass

from hypothesis import given
from hypothesis import strategies as st

from labrig.protocol.realtime import DEGRADED, REALTIME_RETRIES, SHORT, Shortfall, record_in_real_time
from labrig.protocol.safety import StopRequest


@dataclass(frozen=True)
class Run:
    status: str
    reason: str = ""
    fell_behind: str = ""
    late_twin: str = ""
    degraded: str = ""


def _recorder(results: list[Run]) -> tuple[list[int], object, object]:
    calls: list[int] = []
    readied: list[int] = []

    def record() -> Run:
        calls.append(1)
        return results[min(len(calls), len(results)) - 1]

    return calls, record, lambda: readied.append(1)


def test_a_run_that_fell_behind_is_recorded_again_until_it_keeps_up() -> None:
    calls, record, ready = _recorder([Run("complete", fell_behind="camera stream ends 0.80 s early"), Run("complete")])
    assert record_in_real_time(record, ready) == Run("complete")  # type: ignore[arg-type]
    assert len(calls) == 2


def test_a_run_that_falls_behind_every_time_is_kept_marked_short() -> None:
    behind = Run("complete", fell_behind="F/T frames missing for 2.50 s")
    calls, record, ready = _recorder([behind])
    outcome = record_in_real_time(record, ready)  # type: ignore[arg-type]
    assert len(calls) == 1 + REALTIME_RETRIES
    assert outcome.status == SHORT and outcome.fell_behind == behind.fell_behind
    assert f"in {1 + REALTIME_RETRIES} of {1 + REALTIME_RETRIES} tries" in outcome.reason and "F/T" in outcome.reason


def test_aborted_runs_and_a_stop_end_the_tries() -> None:
    calls, record, ready = _recorder([Run("aborted", "force limit", fell_behind="camera stream ends 0.10 s early")])
    assert record_in_real_time(record, ready).status == "aborted" and len(calls) == 1  # type: ignore[arg-type]
    stop = StopRequest()
    stop.request()
    calls, record, ready = _recorder([Run("complete", fell_behind="camera stream ends 0.80 s early")])
    assert record_in_real_time(record, ready, stop).status == SHORT and len(calls) == 1  # type: ignore[arg-type]


@given(st.floats(0, 5), st.floats(0, 5))
def test_a_shortfall_says_what_fell_behind_exactly_when_it_did(camera_s: float, ft_s: float) -> None:
    shortfall = Shortfall(camera_s, ft_s)
    text = shortfall.describe()
    assert bool(text) == shortfall.fell_behind
    assert ("camera" in text) == (camera_s > 0.05) and ("F/T" in text) == (ft_s > 0.1)
    assert shortfall.attrs()["fell_behind"] == text


def test_a_run_a_late_twin_ended_is_recorded_again_and_keeps_its_status_if_it_never_keeps_up() -> None:
    late = Shortfall(late_twin="no status report within 10.0 s")
    ended = Run("aborted", "GRBL: no status report within 10.0 s", late.describe(), late.late_twin)
    calls, record, ready = _recorder([ended, Run("complete")])
    assert record_in_real_time(record, ready) == Run("complete") and len(calls) == 2  # type: ignore[arg-type]
    calls, record, ready = _recorder([Run("failed", "no status report", late.describe(), late.late_twin)])
    outcome = record_in_real_time(record, ready)  # type: ignore[arg-type]
    assert len(calls) == 1 + REALTIME_RETRIES and outcome.status == "failed"
    assert outcome.reason.startswith("no status report") and f"in {1 + REALTIME_RETRIES} of" in outcome.reason
    assert late.fell_behind and "answered late" in late.describe() and late.attrs()["late_twin"] == late.late_twin


def test_a_grbl_timeout_before_the_recording_is_a_late_twin_only_on_the_virtual_rig(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from types import SimpleNamespace

    from labrig.devices.grbl import GrblTimeout
    from labrig.protocol.campaign import _record_one
    from labrig.protocol.spec import ProbeSpec, RecordingPlan

    def run(*args: object, **kwargs: object) -> None:
        raise GrblTimeout("no status report within 10.0 s (last state Idle)")

    plan = RecordingPlan(id="c-000", index=0, spec=ProbeSpec(indenter="sphere", depth_mm=1.0), split="train", repetition=0)
    for virtual in (True, False):
        runner = SimpleNamespace(session=SimpleNamespace(virtual=virtual), run=run)
        outcome = _record_one(runner, plan, tmp_path, "")  # type: ignore[arg-type]
        assert outcome.status == "failed" and "no status report" in outcome.reason
        assert bool(outcome.late_twin) == virtual and bool(outcome.fell_behind) == virtual


def test_a_run_with_damaged_data_is_recorded_again_and_kept_marked_degraded_if_it_stays_damaged() -> None:
    damaged = Run("complete", degraded="the camera's events stop 9.3 s before the protocol ends")
    calls, record, ready = _recorder([damaged, Run("complete")])
    assert record_in_real_time(record, ready) == Run("complete") and len(calls) == 2  # type: ignore[arg-type]
    calls, record, ready = _recorder([damaged])
    outcome = record_in_real_time(record, ready)  # type: ignore[arg-type]
    assert len(calls) == 1 + REALTIME_RETRIES and outcome.status == DEGRADED
    assert "9.3 s" in outcome.reason and "degraded" in outcome.reason
