"""``labrig run --live``: the pipeline on the rig's camera, with a live view, into a result file.

Camera only (hardware, a ``labrig sim serve`` socket, a ``.raw`` replay): until ``--seconds``
or Ctrl-C. With a probing run (``--indenter``, ``--protocol``, ``--at``, ``--depth-mm``; always
on the embedded virtual rig, where nothing else presses the gel): as long as the run lasts,
Ctrl-C stopping the run as in ``labrig record``; the live forces are then compared with the
F/T sensor's. The work is in :mod:`labrig.live.runner` and :mod:`labrig.live.rig`;
this module checks options, shows the live table and prints the summary.
"""

from __future__ import annotations

import json
import signal
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import typer
from rich import box
from rich.live import Live
from rich.markup import escape
from rich.table import Table

from labrig.cli_run import WindowLog, console, err_console, stage_table, window_summary, write_view
from labrig.errors import LabrigError
from labrig.pipeline.windows import WindowSpec

#: Windows kept for --view (the last ones; every --view-every-th).
MAX_VIEW_FRAMES = 300


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

    @property
    def probe_options_given(self) -> bool:
        return any(v is not None for v in (self.indenter, self.protocol, self.at, self.depth_mm, self.save_recording))


def run_live(o: LiveOptions) -> None:
    """Check the options, build the pipeline, stream, print the summary."""
    from labrig.config import DEFAULT_RIG, load_rig
    from labrig.live import rig as live_rig
    from labrig.pipeline import depth_sources, run_setup, runtime
    from labrig.protocol.rigfile import device_config

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
    depth = depth_sources.ModelDepth(o.model or _default_model())
    window_us, window_events = _windows(o, depth.model.window_ms)
    calibration_dir = o.calibration if o.calibration is not None else rig.path.parent
    setup = run_setup.setup_for_rig(rig, calibration_dir=calibration_dir, youngs_modulus_mpa=o.youngs_modulus_mpa)
    pipe = runtime.Pipeline(setup, depth, keep_sae=o.view is not None)
    source = "virtual rig (embedded)" if devices.virtual else f"camera {live_rig.describe_camera(devices)}"
    sink = _Sink(o, len(setup.rest_px), {
        "source": f"live: {source}", "live": 1, "time_base": "camera device time, us", "depth_source": depth.name,
        "window_us": window_us or 0, "window_events": window_events or 0,
        "youngs_modulus_mpa": setup.youngs_modulus_mpa, "poisson_ratio": setup.poisson_ratio,
        "sources": json.dumps(setup.sources)})
    try:
        if probing:
            extra = _with_probe(o, rig, devices, pipe, sink, window_us, window_events, calibration_dir)
        else:
            extra = _camera_only(o, devices, pipe, sink, window_us, window_events)
    finally:
        sink.close()
    stats = extra.pop("stats")
    if not len(sink.log):
        raise LabrigError(f"no windows: no camera events reached the pipeline ({stats.end_reason or 'stopped'}); "
                          "check the camera streams (`labrig devices`, or the `labrig sim serve` terminal)")
    summary = window_summary(extra.pop("recording"), sink.log, stats.wall_s, depth.name, setup, window_us, window_events,
                             o.out, o.view)
    summary.update({"live": True, "source": source, "virtual_rig": devices.virtual, "time_base": "camera device us",
                    **stats.summary(), **extra})
    if o.view is not None:
        write_view(list(sink.frames), setup, o.view)
    if o.as_json:
        print(json.dumps(summary, indent=2))
    else:
        _print(summary)
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
    if o.view is not None and o.view.suffix.lower() != ".gif":
        raise LabrigError("--view writes a GIF: give a path ending in .gif")
    if o.save_recording is not None and o.save_recording.exists():
        raise LabrigError(f"--save-recording {o.save_recording} exists; give a new path")


def _default_model() -> Path:
    from labrig.pipeline.depth_sources import default_model_path

    try:
        return default_model_path()
    except LabrigError:
        raise LabrigError("no depth network (NAME.onnx + NAME.json) in models/, and the live pipeline needs one: "
                          "pass --model X.onnx, or train one with `labrig train DATA/` (it writes models/)") from None


def _windows(o: LiveOptions, trained_ms: float) -> tuple[int | None, int | None]:
    """(window_us, window_events): the network's trained window unless told otherwise."""
    windows = WindowSpec.from_options(o.window_ms, o.window_events, default_ms=trained_ms)
    if windows.window_us is not None and o.window_ms is not None and abs(o.window_ms - trained_ms) > 1e-9:
        err_console.print(f"[yellow]warning:[/] the network was trained on {trained_ms:g} ms windows; "
                          f"--window-ms {o.window_ms:g} gives it SAEs of another span")
    return windows.window_us, windows.window_events


def _max_lag(o: LiveOptions) -> float:
    from labrig.live.runner import MAX_LAG_MS

    return o.max_lag_ms if o.max_lag_ms is not None else MAX_LAG_MS


# -- the two ways to stream --------------------------------------------------------------------------


def _camera_only(o: LiveOptions, devices: Any, pipe: Any, sink: _Sink, window_us: int | None,
                 window_events: int | None) -> dict[str, Any]:
    from labrig.live import rig as live_rig

    stop = threading.Event()

    def on_ctrl_c() -> str:
        stop.set()
        return "[yellow]stopping[/]: closing the result file"

    with live_rig.camera_stream(devices, pipe, window_us=window_us, window_events=window_events,
                                max_lag_ms=_max_lag(o)) as (runner, camera):
        view = LiveView(f"labrig run --live: camera {live_rig.describe_camera(devices)}", runner.stats, o.seconds)
        sink.view = view
        with _ctrl_c(on_ctrl_c), _showing(view, not o.as_json):
            for result in runner.run(seconds=o.seconds, stop=stop):
                sink.take(result)
        dropped = (camera.stats.dropped_chunks, camera.stats.dropped_events)
        error = camera.error
    return {"stats": runner.stats, "recording": None, "dropped_chunks": dropped[0], "dropped_events": dropped[1],
            "camera_error": None if error is None else str(error), "probe": None, "ft_comparison": None}


def _with_probe(o: LiveOptions, rig: Any, devices: Any, pipe: Any, sink: _Sink, window_us: int | None,
                window_events: int | None, calibration_dir: Path) -> dict[str, Any]:
    from labrig.evaluation.measured import ft_axes_in_gel
    from labrig.indenters import DEFAULT_INDENTERS, load_indenters
    from labrig.live import rig as live_rig
    from labrig.protocol import apply_overrides, load_protocol
    from labrig.protocol.files import DEFAULT_PROTOCOL
    from labrig.protocol.runner import ProbeRunner
    from labrig.protocol.safety import StopRequest
    from labrig.protocol.session import RigSession
    from labrig.protocol.spec import ProtocolError

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
    stop = StopRequest()
    session = RigSession.for_rig(rig, indenters[spec.indenter], indenters_path=DEFAULT_INDENTERS,
                                 shear_directions_deg=[spec.shear_direction_deg])
    where = "virtual rig" if devices.virtual else "rig"
    view = LiveView(f"labrig run --live: {spec.indenter} probing run on the {where}", None, None,
                    ft_axes_in_gel(None, calibration_dir)[0])
    sink.view = view
    progress: Callable[[Any], None] = view.on_progress
    runner = ProbeRunner.for_session(session, stop=stop, progress=progress)
    runner.check(spec)  # refuse an unsafe plan before the rig starts
    keep = o.save_recording
    with tempfile.TemporaryDirectory(prefix="labrig-live-") as folder:
        path = keep if keep is not None else Path(folder) / f"{spec.indenter}-live.h5"

        def on_ctrl_c() -> str:
            level = stop.request()
            return "[yellow]stopping after this phase[/] (Ctrl-C again to hold and retract at once)" if level == 1 \
                else "[red]holding and retracting now[/]"

        with session:
            stream = live_rig.ProbeStream(session, runner, spec, path, pipeline=pipe, window_us=window_us,
                                          window_events=window_events, max_lag_ms=_max_lag(o),
                                          protocol_toml=protocol_path.read_text())
            view.stats = stream.live.stats
            with _ctrl_c(on_ctrl_c), _showing(view, not o.as_json):
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


# -- results, view, Ctrl-C -------------------------------------------------------------------------------


class _Sink:
    """Where each live result goes: the result file (opened at the first window), the animation
    frames, the summary rows and the live view."""

    def __init__(self, o: LiveOptions, n_markers: int, attrs: dict[str, Any]) -> None:
        self.out, self.view_path, self.every = o.out, o.view, max(o.view_every, 1)
        self.n_markers, self.attrs = n_markers, attrs
        self.writer: Any = None
        self.frames: deque[Any] = deque(maxlen=MAX_VIEW_FRAMES)
        self.log = WindowLog()
        self.view: LiveView | None = None

    def take(self, r: Any) -> None:
        from labrig.pipeline.results import ResultWriter

        if self.out is not None:
            if self.writer is None:
                self.writer = ResultWriter(self.out, self.n_markers, self.attrs)
            self.writer.write(r)
        if self.view_path is not None and r.index % self.every == 0:
            self.frames.append(r)
        else:
            r.sae = None
        self.log.add(r)
        if self.view is not None:
            self.view.on_result(r)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


class LiveView:
    """The live table: windows, real-time factor, latency, event rate, latest net force (and the
    probing run's phase and F/T force on the gel). Rendered by rich's refresh thread."""

    def __init__(self, title: str, stats: Any, seconds: float | None, ft_to_gel: Any = None) -> None:
        self.title = title
        self.stats = stats
        self.seconds = seconds
        self.ft_to_gel = ft_to_gel
        self.started = time.monotonic()
        self.load: deque[float] = deque(maxlen=100)  # processing time / window span, recent windows
        self.net_n = np.zeros(3)
        self.progress: Any = None
        self._rate = (self.started, 0, 0.0)

    def on_result(self, r: Any) -> None:
        self.load.append(sum(r.seconds.values()) * 1e6 / max(r.t1_us - r.t0_us, 1))
        self.net_n = r.net_force_n

    def on_progress(self, p: Any) -> None:
        self.progress = p

    def _event_rate_hz(self) -> float:
        now, events = time.monotonic(), self.stats.events if self.stats is not None else 0
        t_last, n_last, rate = self._rate
        if now - t_last >= 0.5:
            rate = (events - n_last) / (now - t_last)
            self._rate = (now, events, rate)
        return rate

    def render(self) -> Table:
        s = self.stats
        table = Table(title=self.title, title_justify="left", box=box.SIMPLE_HEAD)
        for name in ("time s", "windows", "skipped", "late", "RTF", "latency ms", "Mev/s", "net force on gel N"):
            table.add_column(name, justify="right", no_wrap=True)
        elapsed = time.monotonic() - self.started
        latency = s.latency_ms[-50:] if s is not None else []
        row = [f"{elapsed:.1f}" + (f"/{self.seconds:g}" if self.seconds else ""),
               str(s.windows if s else 0), str(s.skipped if s else 0), str(s.late if s else 0),
               f"{np.median(self.load):.2f}" if self.load else "-",
               f"{np.median(latency):.1f}" if latency else "-", f"{self._event_rate_hz() / 1e6:.2f}", _xyz(self.net_n)]
        if self.ft_to_gel is not None:
            from labrig.evaluation.measured import ft_on_gel_n

            table.add_column("phase", no_wrap=True)
            table.add_column("F/T on gel N", justify="right", no_wrap=True)
            p = self.progress
            row += [p.phase if p else "starting", _xyz(ft_on_gel_n(p.force_n, self.ft_to_gel)) if p else "-"]
        table.add_row(*row)
        return table


def _xyz(v: Any) -> str:
    return " ".join(f"{float(x):+6.2f}" for x in v)


@contextmanager
def _showing(view: LiveView, enabled: bool) -> Iterator[None]:
    if not enabled:
        yield
        return
    with Live(get_renderable=view.render, console=err_console, refresh_per_second=4, transient=True):
        yield


@contextmanager
def _ctrl_c(action: Callable[[], str]) -> Iterator[None]:
    """Ctrl-C runs ``action`` (and prints what it returns) instead of raising KeyboardInterrupt."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        err_console.print(action())

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


# -- the summary -----------------------------------------------------------------------------------------


def _print(s: dict[str, Any]) -> None:
    console.print(f"[bold]labrig run --live[/]: {escape(s['source'])}, {escape(s['depth_source'])} depth")
    console.print(stage_table(s["stage_median_ms"]))
    mode = f"{s['window_events']} events" if s["window_events"] else f"{s['window_us'] / 1000:g} ms"
    console.print(f"{s['windows_tracked']} windows of {mode} tracked over {s['stream_s']:.2f} s of camera time "
                  f"(wall {s['stream_wall_s']:.2f} s, {s['end_reason']}): {s['windows_processed']} with forces, "
                  f"{s['windows_skipped']} skipped (tracked only), {s['windows_late']} late")
    style = "green" if not s["windows_skipped"] and not s["dropped_chunks"] else "yellow"
    console.print(f"[{style}]processing {s['processing_per_window_ms']:.2f} ms per window (real-time factor "
                  f"{s['real_time_factor']:.2f}); latency median {s['latency_median_ms']:.1f} ms, p95 "
                  f"{s['latency_p95_ms']:.1f} ms; dropped chunks {s['dropped_chunks']}[/]")
    f = s["peak_net_force_n"]
    console.print(f"peak normal force {s['peak_normal_force_n']:.2f} N (net {f[0]:+.2f}, {f[1]:+.2f}, {f[2]:+.2f} N, "
                  f"on the gel); E = {s['youngs_modulus_mpa']:.3g} MPa from {escape(s['sources']['modulus'])}")
    if s["camera_error"]:
        console.print(f"[yellow]the camera stream ended with an error: {escape(s['camera_error'])}[/]")
    c, p = s["ft_comparison"], s["probe"]
    if p is not None:
        style = "green" if p["exit_status"] == "complete" else "yellow"
        where = "virtual rig" if s["virtual_rig"] else "rig"
        console.print(f"probing run on the {where}: [{style}]{p['exit_status']}[/]" + (f" ({p['reason']})" if p["reason"] else "")
                      + f"; recording {'kept at ' + p['recording'] if p['recording'] else 'compared, then deleted'}")
    if c is not None:
        ratio = f"{c['peak_normal_force_ratio']:.2f}" if c["peak_normal_force_ratio"] is not None else "-"
        corr = f"{c['normal_force_correlation']:.2f}" if c["normal_force_correlation"] is not None else "-"
        console.print(f"against the F/T sensor (force on the gel, gel frame; {c['windows_compared']} windows): peak "
                      f"normal force {c['pipeline_peak_normal_force_n']:.2f} N live vs {c['ft_peak_normal_force_n']:.2f} N "
                      f"F/T (ratio {ratio}); Fz RMS error {c['normal_force_rms_error_n']:.2f} N, correlation {corr}")
    for key in ("out", "view"):
        if s[key]:
            console.print(f"{key}: {s[key]}")
