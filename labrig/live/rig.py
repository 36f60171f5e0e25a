"""Live pipeline sources on the rig: the configured camera alone, or a probing run's camera stream.

* :func:`camera_stream`: the camera of the rig file's ``[devices]`` (``metavision`` hardware,
  a ``sim`` socket of ``labrig sim serve``, or a ``raw`` file replayed in real time), read
  directly by a :class:`~labrig.live.runner.LiveRunner`.
* :class:`ProbeStream`: one probing run (:class:`~labrig.protocol.runner.ProbeRunner`) on an
  open :class:`~labrig.protocol.session.RigSession` in a background thread, while the live
  pipeline reads the same camera chunks through a :class:`~labrig.live.sources.ChunkTap`
  registered as the session's chunk listener. The run records as ``labrig record`` does (the
  recording path is untouched); that recording's F/T samples are then the reference for
  :func:`compare_with_ft`. A run whose force loop reads the event sensor (``feedback = "events"``) gets each
  window's forces as they come (:class:`~labrig.protocol.feedback.EstimateFeedback`).

Forces: the pipeline's are on the gel (pressing: Fz < 0), gel frame; the F/T sensor reads
the force on the indenter in its own axes, so it is rotated into the gel frame (rig
registration) and negated before any comparison.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.devices.camera import Camera, CameraError, open_camera
from labrig.errors import LabrigError
from labrig.evaluation.measured import ft_axes_in_gel, measured_force_on_gel_n
from labrig.live.runner import MAX_LAG_MS, LiveRunner
from labrig.live.sources import ChunkTap
from labrig.pipeline.runtime import Pipeline, WindowResult
from labrig.pipeline.windows import DEFAULT_WINDOW_US
from labrig.protocol.feedback import Estimate, EstimateFeedback
from labrig.protocol.rigfile import DeviceConfig
from labrig.protocol.runner import ProbeRunner, RunResult
from labrig.protocol.session import RigSession
from labrig.protocol.spec import ProbeSpec
from labrig.recording import Recording

F64 = npt.NDArray[np.float64]


# -- the camera alone -------------------------------------------------------------------------------


def describe_camera(devices: DeviceConfig) -> str:
    """Which camera a camera-only live run reads, for messages and result files."""
    where = devices.camera_path or ("first found" if devices.camera == "metavision" else "")
    return f"{devices.camera} {where}".strip()


def check_camera(devices: DeviceConfig) -> None:
    """Refuse a ``[devices]`` camera that cannot be there (no socket, no file) before anything heavy loads."""
    if devices.virtual:
        raise LabrigError("no camera configured in the rig file's [devices]: the embedded virtual rig needs a probing run")
    if devices.camera == "sim" and not Path(devices.camera_path).exists():
        raise CameraError(f"[devices] camera_path {devices.camera_path}: no such socket; start `labrig sim serve "
                          "--links DIR` and set camera_path to DIR/evk4")
    if devices.camera_is_file and not Path(devices.camera_path).is_file():
        raise CameraError(f"[devices] camera = \"metavision\" opens camera_path {devices.camera_path} through the SDK's "
                          "file device, but it is not a file: name a .raw recording, or a camera serial")
    if devices.camera == "raw" and not Path(devices.camera_path or "").is_file():
        raise CameraError(f"[devices] camera = \"raw\" replays camera_path, but {devices.camera_path or '(empty)'} "
                          "is not a file: name a .raw recording")


def open_live_camera(devices: DeviceConfig, *, connect_timeout_s: float = 2.0) -> Camera:
    """The ``[devices]`` camera, open and streaming. Not for the embedded virtual rig (no camera
    exists before its rig starts: use :class:`ProbeStream`). ``raw`` replays in real time."""
    check_camera(devices)
    options = devices.camera_options()
    if devices.camera == "sim":
        options["connect_timeout_s"] = connect_timeout_s
    elif devices.camera == "raw":
        options["speed"] = 1.0
    camera = open_camera(devices.camera, **options)
    try:
        camera.open()
        camera.start()
    except BaseException:
        camera.close()
        raise
    return camera


@contextmanager
def camera_stream(devices: DeviceConfig, pipeline: Pipeline, *, window_us: int | None = DEFAULT_WINDOW_US,
                  window_events: int | None = None, max_lag_ms: float | None = MAX_LAG_MS
                  ) -> Iterator[tuple[LiveRunner, Camera]]:
    """(live runner, camera) on the ``[devices]`` camera; the camera is closed on exit."""
    camera = open_live_camera(devices)
    try:
        yield LiveRunner(pipeline, camera, window_us=window_us, window_events=window_events,
                         max_lag_ms=max_lag_ms), camera
    finally:
        camera.close()


# -- a probing run alongside ------------------------------------------------------------------------


class ProbeStream:
    """One probing run in a background thread while :attr:`live` streams the session's camera.

    ``results()`` starts the run and yields the live results until the run is over (the tap
    closes after the run's recording has its last events); :meth:`outcome` returns the run's
    result or raises its error. If the consumer fails, the run is asked to stop after its
    current phase (it retracts and finalizes its recording) and is waited for.
    """

    def __init__(self, session: RigSession, runner: ProbeRunner, spec: ProbeSpec, recording: str | Path, *,
                 pipeline: Pipeline, window_us: int | None = DEFAULT_WINDOW_US, window_events: int | None = None,
                 max_lag_ms: float | None = MAX_LAG_MS, protocol_toml: str = "") -> None:
        self.session = session
        self.runner = runner
        self.spec = spec
        self.recording = Path(recording)
        self.protocol_toml = protocol_toml
        self.tap = ChunkTap()
        self.live = LiveRunner(pipeline, self.tap, window_us=window_us, window_events=window_events,
                               max_lag_ms=max_lag_ms)
        if spec.reads_events:
            runner.estimate = EstimateFeedback()
        self._result: RunResult | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="labrig-live-probe", daemon=True)

    def _run(self) -> None:
        try:
            self._result = self.runner.run(self.spec, self.recording, protocol_toml=self.protocol_toml)
        except BaseException as exc:  # handed to outcome()
            self._error = exc
        finally:
            self.tap.close()

    def results(self) -> Iterator[WindowResult]:
        self.runner.check(self.spec)  # refuse an unsafe plan before anything streams
        self.session.add_chunk_listener(self.tap)
        self._thread.start()
        finished = False
        try:
            for result in self.live.run():
                self._publish(result)
                yield result
            finished = True
        finally:
            if not finished and self.runner.stop.level == 0:
                self.runner.stop.request()
            self._thread.join()
            self.session.remove_chunk_listener(self.tap)

    def _publish(self, result: WindowResult) -> None:
        """A window's forces to the run's force loop (``feedback = "events"``), stamped with the window's end on
        the host clock: the recording's camera clock model once it has one, else the lower envelope of the
        chunks' arrivals."""
        estimate = self.runner.estimate
        if estimate is None:
            return
        t_ns = self.session.camera_host_ns(result.t1_us)
        if t_ns is None:
            offset_us = self.live.stats.camera_offset_us
            if offset_us is None:
                return
            t_ns = round((result.t1_us + offset_us) * 1000)
        estimate.publish(Estimate(t_ns, np.asarray(result.net_force_n, np.float64),
                                  np.asarray(result.forces_n, np.float64),
                                  np.asarray(result.displacement_mm, np.float64)))

    def outcome(self) -> RunResult:
        if self._error is not None:
            raise self._error
        if self._result is None:
            raise LabrigError("the probing run did not start")
        return self._result


# -- against the F/T sensor ---------------------------------------------------------------------------


def compare_with_ft(recording: str | Path, t0_device_us: npt.ArrayLike, t1_device_us: npt.ArrayLike,
                    net_force_n: npt.ArrayLike, calibration_dir: str | Path | None) -> dict[str, Any]:
    """The live net forces (W, 3) of device-time windows against the recording's F/T sensor.

    Windows map to the recording's host clock through its camera clock model; those outside
    the recording (before it began: travel, tare) are left out. The F/T force of a window is
    its mean tared sample, rotated into the gel frame and negated (on the gel). Peaks are
    normal forces (-Fz, N) of window means.
    """
    net = np.asarray(net_force_n, np.float64).reshape(-1, 3)
    with Recording(recording) as rec:
        rotation, axes_source = ft_axes_in_gel(rec, calibration_dir)
        camera = rec.clock_model("camera")
        t0 = camera.to_host_us_int(np.asarray(t0_device_us, np.int64))
        t1 = camera.to_host_us_int(np.asarray(t1_device_us, np.int64))
        inside = (t0 >= 0) & (t1 <= rec.end_us())
        if not inside.any():
            raise LabrigError(f"{recording}: no live window falls inside the recording; cannot compare with the F/T sensor")
        ft = measured_force_on_gel_n(rec, t0[inside], t1[inside], rotation)
    live = net[inside]
    live_peak, ft_peak = float(-live[:, 2].min()) + 0.0, float(-ft[:, 2].min()) + 0.0  # + 0.0: no "-0.0"
    error = live - ft
    both_vary = live[:, 2].std() > 0 and ft[:, 2].std() > 0
    return {
        "windows_compared": int(inside.sum()), "ft_axes": axes_source,
        "pipeline_peak_normal_force_n": live_peak, "ft_peak_normal_force_n": ft_peak,
        "peak_normal_force_ratio": live_peak / ft_peak if ft_peak > 0 else None,
        "normal_force_rms_error_n": float(np.sqrt(np.mean(error[:, 2] ** 2))),
        "shear_force_rms_error_n": float(np.sqrt(np.mean(np.sum(error[:, :2] ** 2, axis=1)))),
        "normal_force_correlation": float(np.corrcoef(live[:, 2], ft[:, 2])[0, 1]) if both_vary else None,
    }
