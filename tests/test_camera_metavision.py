"""The metavision camera backend: against the fake SDK (labrig.testing.fake_metavision, written from
OpenEB's sources) always, and against the real ``metavision_hal`` when it is importable."""

from __future__ import annotations

import importlib.util
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labrig.devices.camera import (
    SDK_MISSING,
    CameraError,
    MetavisionCamera,
    metavision_sdk,
    open_camera,
)
from labrig.devices.raw import TRIGGER_DTYPE, encode_evt3, read_raw
from labrig.eventtypes import EVENT_DTYPE
from labrig.protocol.routing import record_camera
from labrig.testing.fake_metavision import Channel, FakeCamera, fake_metavision_hal

pytestmark = pytest.mark.usefixtures("time_limit_20s")

SAMPLES = Path(os.environ.get("LABRIG_EVT_DATA", Path(__file__).resolve().parents[2] / "shared" / "data" / "evt"))
REAL_SDK = importlib.util.find_spec("metavision_hal") is not None


def make_events(n: int, t0: int, span_us: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(t0, t0 + span_us, n))
    ev["x"] = rng.integers(0, 1280, n)
    ev["y"] = rng.integers(0, 720, n)
    ev["p"] = rng.integers(0, 2, n)
    return ev


def edges(rows: list[tuple[int, int, int]]) -> np.ndarray:
    tr = np.zeros(len(rows), TRIGGER_DTYPE)
    for i, (t, p, channel) in enumerate(rows):
        tr[i] = (p, t, channel)
    return tr


def evt3_shift_us(t0_us: int) -> int:
    """OpenEB's EVT3 time shift for a stream whose first TIME_HIGH holds ``t0_us``: (TIME_HIGH - 1) * 4096."""
    return ((t0_us >> 12) - 1) << 12


def drain(cam: Any, timeout_s: float = 3.0) -> tuple[np.ndarray, np.ndarray, int]:
    """Everything until the stream ends (raising what read() raises); (events, triggers, chunks)."""
    evs, trs, n = [], [], 0
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        chunk = cam.read(timeout_s=0.2)
        if chunk is None:
            if cam.ended:
                break
            continue
        evs.append(chunk.events)
        trs.append(chunk.triggers)
        n += 1
    ev = np.concatenate(evs) if evs else np.zeros(0, EVENT_DTYPE)
    tr = np.concatenate(trs) if trs else np.zeros(0, TRIGGER_DTYPE)
    return ev, tr, n


@pytest.fixture
def sdk(monkeypatch: pytest.MonkeyPatch) -> Any:
    """Installs a fake SDK seeing one EVK4 and returns (module, camera)."""
    camera = FakeCamera()
    hal = fake_metavision_hal([camera])
    monkeypatch.setitem(sys.modules, "metavision_hal", hal)
    return hal, camera


def test_camera_streams_its_buffers_and_an_unplug_is_an_error(sdk: Any) -> None:
    hal, camera = sdk
    ev = make_events(6000, 100_000, 3000)
    tr = edges([(100_500, 1, 0), (101_500, 0, 0)])
    payload = encode_evt3(ev, tr)
    for i in range(0, len(payload), 1002):  # odd sizes split EVT3 words and vectors across buffers
        camera.push(payload[i : i + 1002])
    with open_camera("metavision", serial="") as cam:
        assert isinstance(cam, MetavisionCamera)
        device = hal.opened[0]
        assert cam.info.serial == "00ca0009" and cam.info.sensor == "IMX636" and cam.info.source == "USB"
        assert cam.info.fields["Integrator"] == "Prophesee" and "integrator" not in cam.info.fields
        assert cam.trigger_inputs() == {"main": 0} and device.trigger_in.enabled == {Channel.MAIN}
        cam.set_bias("bias_diff_off", 30)
        cam.set_roi(10, 20, 300, 400)
        assert device.biases.values["bias_diff_off"] == 30 and device.roi.window == (10, 20, 300, 400) and device.roi.enabled
        with pytest.raises(CameraError, match="trigger input 'aux'"):
            cam.enable_trigger_in("aux")  # an EVK4 has the main input only
        with pytest.raises(CameraError, match="trigger channel 1"):
            cam.enable_trigger_in(1)
        cam.start()
        time.sleep(0.2)
        camera.unplug()
        with pytest.raises(CameraError, match="stopped streaming"):
            drain(cam)
        assert cam.ended and cam.error is not None
    inside = (ev["x"] >= 10) & (ev["x"] < 310) & (ev["y"] >= 20) & (ev["y"] < 420)
    assert cam.stats.events == int(inside.sum()) and cam.stats.triggers == 2
    assert device.stream.poll_buffer() == -1


def test_events_and_triggers_arrive_exactly_with_the_sdk_time_shift(sdk: Any) -> None:
    _, camera = sdk
    ev = make_events(5000, 200_000, 4000, seed=3)
    tr = edges([(200_100, 1, 0), (202_000, 0, 0)])
    payload = encode_evt3(ev, tr)
    for i in range(0, len(payload), 777):
        camera.push(payload[i : i + 777])
    got_ev, got_tr = [], []
    with open_camera("metavision") as cam:
        cam.start()
        deadline = time.monotonic() + 3
        while sum(e.size for e in got_ev) < ev.size and time.monotonic() < deadline:
            chunk = cam.read(timeout_s=0.2)
            if chunk is not None:
                got_ev.append(chunk.events)
                got_tr.append(chunk.triggers)
    shift = evt3_shift_us(200_000)
    events, triggers = np.concatenate(got_ev), np.concatenate(got_tr)
    assert events.dtype == EVENT_DTYPE and triggers.dtype == TRIGGER_DTYPE
    for name in ("x", "y", "p"):
        assert np.array_equal(events[name], ev[name])
    assert np.array_equal(events["t"], ev["t"] - shift)
    # the SDK hands trigger arrays over as views it reuses: the adapter's copies must be intact
    assert np.array_equal(triggers["t"], tr["t"] - shift) and triggers["p"].tolist() == [1, 0]
    assert triggers["id"].tolist() == [0, 0]


def test_trigger_ids_follow_what_the_device_reports(monkeypatch: pytest.MonkeyPatch) -> None:
    """An EVK2's main input carries id 1: 'main' maps to it, edges of other ids are not delivered."""
    camera = FakeCamera(serial="evk2", sensor="Gen3.1", trigger_ids={Channel.MAIN: 1})
    monkeypatch.setitem(sys.modules, "metavision_hal", fake_metavision_hal([camera]))
    ev = make_events(500, 50_000, 1000)
    camera.push(encode_evt3(ev, edges([(50_100, 1, 1), (50_200, 1, 0), (50_300, 0, 1)])))
    with open_camera("metavision", serial="evk2") as cam:
        assert cam.trigger_inputs() == {"main": 1} and cam.trigger_channels == {1}
        cam.start()
        got = []
        deadline = time.monotonic() + 3
        while sum(t.size for t in got) < 2 and time.monotonic() < deadline:
            chunk = cam.read(timeout_s=0.2)
            if chunk is not None:
                got.append(chunk.triggers)
    triggers = np.concatenate(got)
    assert triggers["id"].tolist() == [1, 1] and triggers["p"].tolist() == [1, 0]


def test_a_failing_stream_reaches_the_caller(sdk: Any, tmp_path: Path) -> None:
    """A decode error in the reader thread is raised by read() and by record_camera, never a quiet end."""
    from labrig.recording import RecordingWriter

    hal, camera = sdk
    camera.push(encode_evt3(make_events(300, 10_000, 500), edges([])))
    with open_camera("metavision") as cam:
        device = hal.opened[0]

        def broken(raw: Any) -> None:
            raise RuntimeError("decoder exploded")

        device.stream_decoder.decode = broken
        with RecordingWriter(tmp_path / "cam.h5", min_free_bytes=None) as writer:
            with pytest.raises(CameraError, match="decoder exploded"):
                record_camera(cam, writer, threading.Event())
    assert cam.ended


def test_a_raw_file_through_the_sdk_file_device(sdk: Any, tmp_path: Path) -> None:
    """camera_path = FILE.raw: the SDK's file device; the stream ends at the file's end, not as an error."""
    from labrig.devices.raw import write_raw

    ev = make_events(20_000, 3_000_000, 50_000, seed=5)
    tr = edges([(3_010_000, 1, 0), (3_020_000, 0, 0)])
    path = tmp_path / "rec.raw"
    write_raw(path, ev, tr, header={"serial_number": "00ca0042"})
    with open_camera("metavision", path=path) as cam:
        assert cam.info.source == "File" and cam.info.serial == "00ca0042"
        cam.set_roi(0, 0, 640, 720)  # no I_ROI on a file: applied in software
        cam.start()
        got_ev, got_tr, n_chunks = drain(cam)
    left = ev["x"] < 640
    shift = evt3_shift_us(3_000_000)
    assert np.array_equal(got_ev["x"], ev["x"][left]) and np.array_equal(got_ev["t"], ev["t"][left] - shift)
    assert np.array_equal(got_tr["t"], tr["t"] - shift) and n_chunks >= 2 and cam.error is None
    with pytest.raises(CameraError, match="no such RAW file"):
        MetavisionCamera(path=tmp_path / "missing.raw").open()


@pytest.mark.parametrize("name", ["evt3_sample.raw", "evt2_sample.raw"])
def test_the_real_samples_through_the_fake_file_device(sdk: Any, name: str) -> None:
    path = SAMPLES / name
    if not path.is_file():
        pytest.skip(f"real RAW samples not found at {SAMPLES} (set LABRIG_EVT_DATA)")
    _compare_with_read_raw(path)


def _compare_with_read_raw(path: Path) -> None:
    expected = read_raw(path)
    with open_camera("metavision", path=path) as cam:
        cam.start()
        got, _, n_chunks = drain(cam, timeout_s=15)
    assert n_chunks >= 1 and got.size == expected.events.size
    for name in ("x", "y", "p"):
        assert np.array_equal(got[name], expected.events[name])
    offsets = expected.events["t"] - got["t"]
    assert np.all(offsets == offsets[0]) and offsets[0] >= 0  # the SDK's time shift, one constant


@pytest.mark.skipif(not REAL_SDK, reason="the Metavision SDK / OpenEB (metavision_hal) is not importable here; "
                    "see docs/camera.md, 'Metavision SDK', to build it and run this test")
@pytest.mark.parametrize("name", ["evt3_sample.raw", "evt2_sample.raw"])
def test_the_real_sdk_streams_the_real_samples(name: str) -> None:
    path = SAMPLES / name
    if not path.is_file():
        pytest.skip(f"real RAW samples not found at {SAMPLES} (set LABRIG_EVT_DATA)")
    _compare_with_read_raw(path)


def test_without_the_sdk_or_a_camera(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "metavision_hal", None)  # import raises ImportError
    with pytest.raises(CameraError, match="needs the Metavision SDK / OpenEB from Prophesee"):
        MetavisionCamera().open()
    assert "Metavision SDK / OpenEB" in SDK_MISSING
    status = metavision_sdk()
    assert not status.importable and "import failed" in status.error
    monkeypatch.setitem(sys.modules, "metavision_hal", fake_metavision_hal([]))
    with pytest.raises(CameraError, match="no camera with serial 123"):
        MetavisionCamera("123").open()


def test_biases_out_of_the_recommended_range_are_refused(sdk: Any) -> None:
    with open_camera("metavision") as cam:
        with pytest.raises(CameraError, match="recommended range for the IMX636"):
            cam.set_bias("bias_diff", 40)  # allowed by the sensor (up to 200), not recommended by OpenEB
        cam.set_bias("bias_diff", 20)
        assert cam.get_bias("bias_diff") == 20


def test_sdk_status_lists_plugins_and_cameras(sdk: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "libhal_plugin_prophesee.so").write_bytes(b"")
    (tmp_path / "libmetavision_psee_hw_layer.so").write_bytes(b"")
    monkeypatch.setenv("MV_HAL_PLUGIN_PATH", str(tmp_path))
    status = metavision_sdk()
    assert status.importable and status.cameras == ("00ca0009",)
    assert status.plugins == ("libhal_plugin_prophesee.so",) and str(tmp_path) in status.plugin_dirs


def test_labrig_devices_says_what_the_sdk_offers(sdk: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import json

    from typer.testing import CliRunner

    from labrig.cli import app

    (tmp_path / "libhal_plugin_prophesee.so").write_bytes(b"")
    monkeypatch.setenv("MV_HAL_PLUGIN_PATH", str(tmp_path))
    result = CliRunner().invoke(app, ["devices", "--json"])
    assert result.exit_code == 0, result.output
    sdk_entry = json.loads(result.stdout)["metavision_sdk"]
    assert sdk_entry["importable"] and sdk_entry["cameras"] == ["00ca0009"]
    assert sdk_entry["plugins"] == ["libhal_plugin_prophesee.so"]
    text = CliRunner().invoke(app, ["devices"]).stdout
    assert "Metavision SDK: metavision_hal imports" in text and "libhal_plugin_prophesee.so" in text
