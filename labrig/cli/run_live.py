"""``labrig run --live``: the pipeline on the rig's camera, with a live view, into a result file.

Camera only (hardware, a ``labrig sim serve`` socket, a ``.raw`` replay): until ``--seconds``
or Ctrl-C. With a probing run (``--indenter``, ``--protocol``, ``--at``, ``--depth-mm``; always
on the embedded virtual rig, where nothing else presses the gel): as long as the run lasts,
Ctrl-C stopping the run as in ``labrig record``; the live forces are then compared with the
F/T sensor's. The work is in :mod:`labrig.live.runner` and :mod:`labrig.live.rig`;
this module checks options, shows the live table (:mod:`labrig.cli.live_view`) and prints the summary.
"""

from __future__ import annotations

import json
import os
import tempfile
import threading
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from labrig.calibration.ft_frame import ft_axes_in_gel
from labrig.cli.console import err_console, on_ctrl_c, print_json, stop_probing_run
from labrig.cli.live_view import LiveView, showing
from labrig.cli.run_report import check_view, depth_every_option, print_live_run
from labrig.config import DEFAULT_RIG, RigConfig, load_rig
from labrig.errors import LabrigError
from labrig.indenters import DEFAULT_INDENTERS, load_indenters
from labrig.live import rig as live_rig
from labrig.live.runner import MAX_LAG_MS
from labrig.pipeline import depth_sources, run_setup, runtime
from labrig.pipeline.results import ResultWriter
from labrig.pipeline.run_summary import WindowLog, window_summary
from labrig.pipeline.view import write_view
from labrig.pipeline.windows import WindowSpec
from labrig.protocol import apply_overrides, load_protocol
from labrig.protocol.files import DEFAULT_PROTOCOL, on_virtual_camera
from labrig.protocol.rigfile import DeviceConfig, device_config
from labrig.protocol.runner import ProbeRunner
from labrig.protocol.safety import StopRequest
from labrig.protocol.session import RigSession
from labrig.protocol.spec import ProtocolError

if TYPE_CHECKING:
    from labrig.live.view_server import ViewServer

#: Windows kept for --view (the last ones; every --view-every-th).
MAX_VIEW_FRAMES = 300
#: With one core, the network's parts when depth runs less often than every window (one part per window).
ONE_CORE_DEPTH_PARTS = 3


def depth_lane_for(depth_every_us: int | None, cores: int) -> str:
    """Where the network runs live: "window" (every window runs it), "thread" (depth every few windows, a second
    core to run it on) or "steps" (depth every few windows on one core: a part per window)."""
    if depth_every_us is None:
        return "window"
    return "thread" if cores >= 2 else "steps"


def usable_cores() -> int:
    """The CPUs this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


@dataclass(frozen=True)
class LiveOptions:
    """``labrig run --live``'s options, as given (None: not given)."""

    window_ms: float | None
    window_events: int | None
    depth: str | None
    model: Path | None
    out: Path | None
    view: Path | None
    view_every: int
    calibration: Path | None
    rig_path: Path | None
    youngs_modulus_mpa: float | None
    seconds: float | None
    indenter: str | None
    protocol: Path | None
    at: str | None
    depth_mm: float | None
    save_recording: Path | None
    max_lag_ms: float | None
    as_json: bool
    depth_every_ms: float | None = None
    view_server_port: int | None = None  # --view-server: serve the live view on this port (0: any free one)
    view_hz: float = 100.0  # --view-hz: the most windows a second the view sends (0: every window)

    @property
    def probe_options_given(self) -> bool:
        return any(v is not None for v in (self.indenter, self.protocol, self.at, self.depth_mm, self.save_recording))


def run_live(o: LiveOptions) -> None:
    """Check the options, build the pipeline, stream, print the summary."""
    _check(o)
    rig = load_rig(o.rig_path or DEFAULT_RIG)
    devices = device_config(rig)
    probing = devices.virtual or o.probe_options_given
    if probing and o.seconds is not None:
        where = "on the embedded virtual rig the live run is one probing run" if devices.virtual else \
            "with --indenter/--protocol/--at/--depth-mm the live run is one probing run"
        raise LabrigError(f"--seconds: {where}, which lasts its protocol (shorten it there), or Ctrl-C to stop it")
    if not probing:
        live_rig.check_camera(devices)
    calibration_dir = o.calibration if o.calibration is not None else rig.path.parent
    setup = run_setup.setup_for_rig(rig, calibration_dir=calibration_dir, youngs_modulus_mpa=o.youngs_modulus_mpa)
    depth = depth_sources.depth_source("model", setup, model_path=o.model or _default_model())
    assert isinstance(depth, depth_sources.ModelDepth)
    window_us, window_events = _windows(o, depth.model.window_ms)
    depth_every_us = depth_every_option(o.depth_every_ms)
    lane = depth_lane_for(depth_every_us, usable_cores())
    pipe = runtime.Pipeline(setup, depth, keep_sae=o.view is not None, depth_every_us=depth_every_us,
                            depth_lane=lane == "thread", depth_parts=ONE_CORE_DEPTH_PARTS if lane == "steps" else None)
    pipe.warm_up()  # before the stream starts: a first window's kernel loads would delay the windows behind it
    source = "virtual rig (embedded)" if devices.virtual else f"camera {live_rig.describe_camera(devices)}"
    sink = _Sink(o, len(setup.rest_px), {
        "source": f"live: {source}", "live": 1, "time_base": "camera device time, us", "depth_source": depth.name,
        "window_us": window_us or 0, "window_events": window_events or 0,
        "depth_every_us": depth_every_us or 0,
        "youngs_modulus_mpa": setup.youngs_modulus_mpa, "poisson_ratio": setup.poisson_ratio,
        "sources": json.dumps(setup.sources)}, rest_mm=setup.rest_mm())
    if o.view_server_port is not None:
        from labrig.live.view_server import ViewServer  # foxglove-sdk loads only for --view-server

        sink.server = ViewServer(setup.rest_mm(), port=o.view_server_port, max_rate_hz=o.view_hz).start()
        err_console.print(f"live view on {sink.server.url} (Foxglove: Open connection, Foxglove WebSocket)",
                          highlight=False)
    try:
        if probing:
            extra = _with_probe(o, rig, devices, pipe, sink, window_us, window_events, calibration_dir)
        else:
            extra = _camera_only(o, devices, pipe, sink, window_us, window_events)
    finally:
        sink.close()
        pipe.close()
    if sink.server is not None:
        extra["view_server"] = asdict(sink.server.stats())
    stats = extra.pop("stats")
    if not len(sink.log):
        raise LabrigError(f"no windows: no camera events reached the pipeline ({stats.end_reason or 'stopped'}); "
                          "check the camera streams (`labrig devices`, or the `labrig sim serve` terminal)")
    summary = window_summary(extra.pop("recording"), sink.log, stats.wall_s, depth.name, setup, window_us, window_events,
                             o.out, o.view)
    summary.update({"live": True, "depth_lane": lane, "source": source, "virtual_rig": devices.virtual,
                    "time_base": "camera device us", **stats.summary(), **extra})
    if o.view is not None:
        write_view(list(sink.frames), setup, o.view)
    if o.as_json:
        print_json(summary)
    else:
        print_live_run(summary)
    if summary["probe"] is not None and summary["probe"]["exit_status"] != "complete":
        raise typer.Exit(1)  # as `labrig record`: the probing run did not complete


def _check(o: LiveOptions) -> None:
    if o.depth == "truth":
        raise LabrigError("--depth truth reads a recording's /truth/depth, which a live stream has not: "
                          "live depth comes from the network (--model X.onnx, default: newest in models/, else bundled)")
    if o.depth not in (None, "model"):
        raise LabrigError(f"--depth {o.depth!r}: live depth comes from the network (model)")
    if o.max_lag_ms is not None and o.max_lag_ms <= 0:
        raise LabrigError(f"--max-lag-ms must be positive, not {o.max_lag_ms:g}")
    if o.seconds is not None and o.seconds <= 0:
        raise LabrigError(f"--seconds must be positive, not {o.seconds:g}")
    WindowSpec.from_options(o.window_ms, o.window_events)  # refused before the network loads
    depth_every_option(o.depth_every_ms)
    check_view(o.view)
    if not (o.view_hz >= 0):
        raise LabrigError(f"--view-hz must be zero (every window) or a positive rate in Hz, not {o.view_hz:g}")
    if o.save_recording is not None and o.save_recording.exists():
        raise LabrigError(f"--save-recording {o.save_recording} exists; give a new path")


def _default_model() -> Path:
    try:
        return depth_sources.default_model_path()
    except LabrigError:
        raise LabrigError("no depth network (NAME.onnx + NAME.json) in models/, and the live pipeline needs one: "
                          "pass --model X.onnx, or train one with `labrig train DATA/` (it writes models/)") from None


def _windows(o: LiveOptions, trained_ms: float) -> tuple[int | None, int | None]:
    """(window_us, window_events): the network's trained window unless told otherwise (its SAE spans the trained
    window whatever the pipeline's: :class:`~labrig.pipeline.front_stage.FrontStage`)."""
    windows = WindowSpec.from_options(o.window_ms, o.window_events, default_ms=trained_ms)
    return windows.window_us, windows.window_events


def _max_lag(o: LiveOptions) -> float:
    return o.max_lag_ms if o.max_lag_ms is not None else MAX_LAG_MS


# -- the two ways to stream --------------------------------------------------------------------------


def _camera_only(o: LiveOptions, devices: DeviceConfig, pipe: runtime.Pipeline, sink: _Sink, window_us: int | None,
                 window_events: int | None) -> dict[str, Any]:
    stop = threading.Event()

    def close_on_ctrl_c() -> str:
        stop.set()
        return "[yellow]stopping[/]: closing the result file"

    with live_rig.camera_stream(devices, pipe, window_us=window_us, window_events=window_events,
                                max_lag_ms=_max_lag(o)) as (runner, camera):
        view = LiveView(f"labrig run --live: camera {live_rig.describe_camera(devices)}", runner.stats, o.seconds)
        sink.view = view
        with on_ctrl_c(close_on_ctrl_c), showing(view, not o.as_json):
            for result in runner.run(seconds=o.seconds, stop=stop):
                sink.take(result)
        dropped = (camera.stats.dropped_chunks, camera.stats.dropped_events)
        error = camera.error
    return {"stats": runner.stats, "recording": None, "dropped_chunks": dropped[0], "dropped_events": dropped[1],
            "camera_error": None if error is None else str(error), "probe": None, "ft_comparison": None}


def _with_probe(o: LiveOptions, rig: RigConfig, devices: DeviceConfig, pipe: runtime.Pipeline, sink: _Sink,
                window_us: int | None, window_events: int | None, calibration_dir: Path) -> dict[str, Any]:
    indenters = load_indenters(DEFAULT_INDENTERS)
    protocol_path = o.protocol or DEFAULT_PROTOCOL
    spec = load_protocol(protocol_path, rig, indenters)
    try:
        spec = apply_overrides(spec, at=o.at, depth=o.depth_mm, indenter=o.indenter, rig=rig, indenters=indenters)
    except ProtocolError as exc:  # the library names record's --depth; here it is --depth-mm
        raise ProtocolError(str(exc).replace("--depth:", "--depth-mm:")) from None
    if devices.virtual:
        err_console.print(f"no hardware configured: one probing run ({spec.indenter}, {protocol_path.name}) on the "
                          "virtual rig (embedded), the live pipeline reading its camera")
        spec, note = on_virtual_camera(spec, protocol_path.read_text())
        if note is not None:
            err_console.print(note, markup=False)
    stop = StopRequest()
    session = RigSession.for_rig(rig, indenters[spec.indenter], indenters_path=DEFAULT_INDENTERS,
                                 shear_directions_deg=[spec.shear_direction_deg])
    where = "virtual rig" if devices.virtual else "rig"
    view = LiveView(f"labrig run --live: {spec.indenter} probing run on the {where}", None, None,
                    ft_axes_in_gel(None, calibration_dir)[0])
    sink.view = view
    if sink.server is not None:  # every F/T sample on the live view, at the sensor's rate, each at its own time
        session.add_ft_listener(sink.server.ft_listener(session.clock))
    runner = ProbeRunner.for_session(session, stop=stop, progress=view.on_progress)
    runner.check(spec)  # refuse an unsafe plan before the rig starts
    keep = o.save_recording
    with tempfile.TemporaryDirectory(prefix="labrig-live-") as folder:
        path = keep if keep is not None else Path(folder) / f"{spec.indenter}-live.h5"
        with session:
            stream = live_rig.ProbeStream(session, runner, spec, path, pipeline=pipe, window_us=window_us,
                                          window_events=window_events, max_lag_ms=_max_lag(o),
                                          protocol_toml=protocol_path.read_text())
            view.stats = stream.live.stats
            with on_ctrl_c(stop_probing_run(stop)), showing(view, not o.as_json):
                for result in stream.results():
                    sink.take(result)
            run = stream.outcome()
            assert session.camera is not None
            camera_drops, camera_error = session.camera.stats, session.camera.error
        log = sink.log
        comparison = live_rig.compare_with_ft(run.path, log.t0_us, log.t1_us, log.net(), calibration_dir) if len(log) else None
    probe = {"indenter": spec.indenter, "protocol": str(protocol_path), "exit_status": run.exit_status,
             "reason": run.reason, "phases": run.phases, "peak_force_sensor_n": list(run.peak_force_n),
             "wall_s": round(run.wall_s, 3), "recording": str(run.path) if keep is not None else None}
    return {"stats": stream.live.stats, "recording": probe["recording"],
            "dropped_chunks": camera_drops.dropped_chunks + stream.tap.stats.dropped_chunks,
            "dropped_events": camera_drops.dropped_events + stream.tap.stats.dropped_events,
            "camera_error": None if camera_error is None else str(camera_error), "probe": probe,
            "ft_comparison": comparison}


# -- results ---------------------------------------------------------------------------------------------


class _Sink:
    """Where each live result goes: the result file (opened at the first window), the animation
    frames, the summary rows and the live view."""

    def __init__(self, o: LiveOptions, n_markers: int, attrs: dict[str, Any], rest_mm: Any = None) -> None:
        self.out, self.view_path, self.every = o.out, o.view, max(o.view_every, 1)
        self.n_markers, self.attrs, self.rest_mm = n_markers, attrs, rest_mm
        self.writer: ResultWriter | None = None
        self.frames: deque[runtime.WindowResult] = deque(maxlen=MAX_VIEW_FRAMES)
        self.log = WindowLog()
        self.view: LiveView | None = None
        self.server: ViewServer | None = None

    def take(self, r: runtime.WindowResult) -> None:
        if self.out is not None:
            if self.writer is None:
                self.writer = ResultWriter(self.out, self.n_markers, self.attrs, rest_mm=self.rest_mm)
            self.writer.write(r)
        if self.view_path is not None and r.index % self.every == 0:
            self.frames.append(r)
        else:
            r.sae = None
        self.log.add(r)
        if self.view is not None:
            self.view.on_result(r)
        if self.server is not None:
            self.server.publish(r)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        if self.server is not None:
            self.server.close()
