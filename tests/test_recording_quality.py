"""Every recording's data quality is judged when it is finalized: damage degrades it, late arrival alone does not."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labrig.recording import Recording, RecordingMetadata, RecordingWriter
from labrig.recording.quality import CLEAN, DEGRADED, Quality, assess, stored_quality
from labrig.testing.synthetic import SyntheticRun, feed_writer

RUN = SyntheticRun(duration_s=3.0, peak_event_rate_hz=4e5, seed=3)


class _Damaging:
    """A writer that loses what a failing link would: camera packets after ``camera_stop_us``, and F/T
    samples inside ``ft_gap_us`` (host times)."""

    def __init__(self, writer: RecordingWriter, camera_stop_us: int | None = None,
                 ft_gap_us: tuple[int, int] | None = None) -> None:
        self.writer = writer
        self.camera_stop_us = camera_stop_us
        self.ft_gap_us = ft_gap_us

    def put_events(self, x: Any, y: Any, p: Any, t_device: Any, t_host: Any) -> Any:
        if self.camera_stop_us is not None and int(np.max(t_host)) > self.camera_stop_us:
            return True
        return self.writer.put_events(x, y, p, t_device, t_host)

    def put(self, stream: str, **columns: Any) -> Any:
        if stream == "ft" and self.ft_gap_us is not None:
            t = np.asarray(columns["t_host_us"])
            keep = (t < self.ft_gap_us[0]) | (t > self.ft_gap_us[1])
            columns = {k: np.asarray(v)[keep] for k, v in columns.items()}
            if not keep.any():
                return True
        return self.writer.put(stream, **columns)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.writer, name)


def record(path: Path, **damage: Any) -> Path:
    metadata = RecordingMetadata(indenter="sphere", protocol_toml="# synthetic\n", extra={"synthetic": True})
    with RecordingWriter(path, metadata) as writer:
        feed_writer(_Damaging(writer, **damage), RUN)
    return path


def test_a_clean_recording_is_clean_and_says_so_in_its_file(small_recording: Path) -> None:
    with Recording(small_recording) as rec:
        assert assess(rec) == Quality() and stored_quality(rec) == Quality()
        assert rec.attrs["quality"] == CLEAN


def test_a_camera_that_stops_early_and_an_ft_gap_degrade_the_recording(tmp_path: Path) -> None:
    path = record(tmp_path / "damaged.h5", camera_stop_us=2_000_000, ft_gap_us=(1_000_000, 1_200_000))
    with Recording(path) as rec:
        quality = stored_quality(rec)
        assert quality is not None and quality.verdict == DEGRADED and rec.attrs["quality"] == DEGRADED
        text = quality.describe()
        assert "camera's events stop" in text and "gaps in the F/T samples" in text
        assert quality == assess(rec)


@pytest.mark.parametrize("stop_s", [1.0, 1.5])
def test_the_camera_stopping_is_measured_in_seconds(tmp_path: Path, stop_s: float) -> None:
    path = record(tmp_path / "short.h5", camera_stop_us=int(stop_s * 1e6))
    with Recording(path) as rec:
        (reason,) = [r for r in assess(rec).reasons if "camera's events stop" in r]
    assert f"{RUN.duration_s - stop_s:.1f} s" in reason


def test_inspect_shows_the_verdict_and_no_false_lateness_alarm(small_recording: Path) -> None:
    from labrig.recording.summary import summarize

    with Recording(small_recording) as rec:
        summary = summarize(rec)
    assert summary["quality"] == CLEAN and summary["quality_reasons"] == [] and summary["warnings"] == []
