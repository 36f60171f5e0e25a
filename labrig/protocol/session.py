"""The rig's devices, open for a series of recordings, their data routed into the current one.

A :class:`RigSession` owns the three drivers (GRBL, Bota, camera) for as long
as a ``labrig record`` or a campaign runs. Their callbacks feed whatever
recording is current (:meth:`RigSession.begin` / :meth:`RigSession.end`) and
the safety monitor, which sees every F/T sample whether recording or not.
:meth:`RigSession.for_rig` opens the rig a rig file describes (its [devices]
and [safety], the virtual rig's contact tables prepared); every procedure that
moves the rig starts there.

With no hardware configured the session starts the virtual rig in a child
process (:class:`~labrig.sim.world_process.WorldProcess`: its twins on ptys
and a Unix socket, as ``labrig sim serve``) and opens it with the same
drivers; it also writes the rig's truth into each recording.

Chunk listeners (:meth:`RigSession.add_chunk_listener`) see every camera chunk too, whether
a recording is current or not, after the recording got it: the live pipeline
(``labrig run --live``) reads the same stream this way instead of opening the camera twice.
F/T listeners (:meth:`RigSession.add_ft_listener`) see every F/T sample the same way, at the
sensor's rate (the live view's ``/ft_sensor/wrench``).
"""

from __future__ import annotations

import contextlib
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np

from labrig.clock import HostClock, MonotonicClock
from labrig.config import RigConfig
from labrig.devices.bota import BotaSensor, BotaSettings
from labrig.devices.bota_stream import FtSample
from labrig.devices.camera import Camera, CameraError, EventChunk, open_camera
from labrig.devices.grbl import Grbl
from labrig.devices.grbl_channel import StatusSample
from labrig.errors import LabrigError
from labrig.indenters import Indenter
from labrig.protocol.rigfile import DeviceConfig, device_config, safety_limits
from labrig.protocol.routing import put_chunk, put_cnc, put_ft, put_gcode
from labrig.protocol.safety import ForceMonitor, SafetyLimits
from labrig.recording import RecordingWriter
from labrig.sim.live import put_truth_rows
from labrig.sim.world_process import WorldProcess, prepare_contact_tables

NS_PER_US = 1000
#: The virtual rig's GRBL twin shares a host that may be loaded: starved of CPU it answers lines and
#: status queries seconds late, which a real controller never does. Its driver waits this long (s)
#: before calling a line or a report lost (hardware keeps GRBL's own deadlines).
TWIN_PATIENCE_S = 10.0



T = TypeVar("T")


class Listeners(Generic[T]):
    """Callbacks handed every item of one stream (camera chunks, F/T samples) on its reader thread, in the order
    added. One that raises is removed: :meth:`notify` returns its exception (the first of the call), and the
    stream goes on."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.callbacks: tuple[Callable[[T], None], ...] = ()

    def __bool__(self) -> bool:
        return bool(self.callbacks)

    def add(self, callback: Callable[[T], None]) -> None:
        with self._lock:
            self.callbacks = (*self.callbacks, callback)

    def remove(self, callback: Callable[[T], None]) -> None:
        with self._lock:
            self.callbacks = tuple(f for f in self.callbacks if f is not callback)

    def notify(self, item: T) -> BaseException | None:
        error: BaseException | None = None
        for callback in self.callbacks:
            try:
                callback(item)
            except Exception as exc:  # a listener's bug must not stop the stream or its recording
                error = error or exc
                self.remove(callback)
        return error


class RigSession:
    """Open devices and routing; use as a context manager (see :meth:`open`)."""

    def __init__(self, rig: RigConfig, devices: DeviceConfig, limits: SafetyLimits, *, seed: int = 0,
                 indenter: Indenter | None = None, indenters_path: Path | None = None,
                 clock: HostClock | None = None, world: Any = None) -> None:
        """``world``: an in-process, started :class:`~labrig.sim.world.LiveWorld` to use as the
        virtual rig instead of a child process (tests inject faults into its twins)."""
        devices.check()
        self.rig = rig
        self.devices = devices
        self.limits = limits
        self.seed = seed
        self.indenter = indenter
        self.indenters_path = indenters_path
        self.clock = clock or MonotonicClock()
        self.world: Any = None
        self._own_world = world is None
        self._injected = world
        self.grbl: Grbl | None = None
        self.ft: BotaSensor | None = None
        self.camera: Camera | None = None
        self.monitor = ForceMonitor(limits, on_trip=self._hold)
        self.tare_n: tuple[float, ...] = (0.0,) * 6
        self._writer: RecordingWriter | None = None
        self._truth_thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._pump: threading.Thread | None = None
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        self.camera_events = 0
        #: The longest gap between F/T samples (sensor us) in the current recording: frames lost.
        self.ft_max_gap_us = 0
        self._last_ft_device_us: int | None = None
        self.last_camera_ns = 0  # host time the newest chunk arrived
        self.last_camera_device_us = -1  # camera time of its newest event
        self._listeners: Listeners[EventChunk] = Listeners()
        self._ft_listeners: Listeners[FtSample] = Listeners()
        #: The first exception a chunk or F/T listener raised (that listener was removed; recording went on).
        self.listener_error: BaseException | None = None

    @classmethod
    def for_rig(cls, rig: RigConfig, indenter: Indenter, *, seed: int = 0, indenters_path: Path | None = None,
                shear_directions_deg: Iterable[float] = (0.0,)) -> RigSession:
        """The session for ``rig``'s devices ([devices]; none: the embedded virtual rig) and limits
        ([safety]) with ``indenter`` mounted, not yet opened. On the virtual rig it first builds (or
        finds cached) the contact tables the indenter needs for the runs' shear directions (deg, gel
        frame); ``seed``: the virtual rig's noise."""
        devices, limits = device_config(rig), safety_limits(rig)
        if devices.virtual:
            prepare_contact_tables(rig, indenter, shear_directions_deg)
        return cls(rig, devices, limits, seed=seed, indenter=indenter, indenters_path=indenters_path)

    @property
    def virtual(self) -> bool:
        return self.devices.virtual

    # -- lifecycle --------------------------------------------------------------------------

    def open(self) -> RigSession:
        """Open the devices (again, after :meth:`close`: a restarted rig)."""
        self._stop.clear()
        try:
            paths = self._device_paths()
            patience: dict[str, Any] = (
                {"response_timeout_s": TWIN_PATIENCE_S, "status_timeout_s": TWIN_PATIENCE_S} if self.virtual else {})
            self.grbl = Grbl(paths["grbl"], baudrate=self.devices.grbl_baud, clock=self.clock,
                             on_sample=self._on_cnc, on_gcode=self._on_gcode, **patience,
                             output_on=self.devices.output_on, output_off=self.devices.output_off)
            self.grbl.connect(reset="none" if self.virtual else "auto")
            self.ft = BotaSensor(paths["bota"], baudrate=self.devices.bota_baud, clock=self.clock,
                                 on_sample=self._on_ft, char_gap_s=0.0 if self.virtual else 0.005)
            self.ft.connect(boot_timeout_s=10)
            self.ft.configure(BotaSettings())
            self.ft.start()
            options = self.devices.camera_options(paths["evk4"])
            self.camera = open_camera(self.devices.camera, clock=self.clock, **options).open()
            self.camera.start()
            self._pump = threading.Thread(target=self._pump_camera, name="labrig-camera-pump", daemon=True)
            self._pump.start()
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        self._stop.set()
        for thread in (self._pump, self._truth_thread):
            if thread is not None:
                thread.join(timeout=5)
        for device in (self.camera, self.ft, self.grbl):
            if device is not None:
                with contextlib.suppress(Exception):
                    device.close()
        if self.world is not None and self._own_world:
            self.world.stop()
        self.world = None
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> RigSession:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _device_paths(self) -> dict[str, str]:
        if not self.virtual:
            return {"grbl": self.devices.grbl_port, "bota": self.devices.bota_port, "evk4": self.devices.camera_path}
        if self._injected is not None:
            self.world = self._injected
            return dict(self.world.paths)
        if self.indenter is None:
            raise LabrigError("the virtual rig needs to know the mounted indenter")
        self._tmp = tempfile.TemporaryDirectory(prefix="labrig-rig-")
        self.world = WorldProcess(self.rig.path, self.indenter.name, indenters_path=self.indenters_path, seed=self.seed,
                                  camera_socket=Path(self._tmp.name) / "evk4.sock").start()
        self._truth_thread = threading.Thread(target=self._pump_truth, name="labrig-truth-pump", daemon=True)
        self._truth_thread.start()
        return self.world.paths

    # -- camera chunk listeners ----------------------------------------------------------------

    def add_chunk_listener(self, listener: Callable[[EventChunk], None]) -> None:
        """Hand every camera chunk to ``listener`` as well, on the camera pump thread, after the
        current recording (if any) got it. ``listener`` must return at once (queue the chunk,
        drop it when full): the pump also feeds the recording. One that raises is removed and its
        exception kept in :attr:`listener_error`; the recording is not affected."""
        self._listeners.add(listener)

    def remove_chunk_listener(self, listener: Callable[[EventChunk], None]) -> None:
        self._listeners.remove(listener)

    def add_ft_listener(self, listener: Callable[[FtSample], None]) -> None:
        """Hand every F/T sample (tared, sensor axes, stamped on :attr:`clock`) to ``listener`` as well, on the
        sensor's reader thread, after the safety monitor and the current recording (if any) got it: at the sensor's
        rate (800 Hz), so ``listener`` must return at once. One that raises is removed and its exception kept in
        :attr:`listener_error`; neither the monitor nor the recording is affected."""
        self._ft_listeners.add(listener)

    def remove_ft_listener(self, listener: Callable[[FtSample], None]) -> None:
        self._ft_listeners.remove(listener)

    def _listener_failed(self, error: BaseException | None) -> None:
        if error is not None and self.listener_error is None:
            self.listener_error = error

    # -- recordings ---------------------------------------------------------------------------

    def begin(self, writer: RecordingWriter) -> None:
        with self._lock:
            self._writer = writer
            self.ft_max_gap_us = 0
            self._last_ft_device_us = None

    def end(self, end_host_ns: int, stall_s: float = 5.0, limit_s: float = 120.0) -> int:
        """Let late data (camera events up to ``end_host_ns``, the rig's truth) arrive, then stop routing.

        Waits as long as the late streams make progress (a camera that lags behind a loaded host
        still delivers everything), at most ``limit_s``; gives up after ``stall_s`` without
        progress. Returns how far (us) the camera stream stopped short of ``end_host_ns``
        (0: it caught up).
        """
        start = time.monotonic()
        last_progress, seen = start, (self.last_camera_device_us, self._world_progress())
        while time.monotonic() - start < limit_s:
            if self.camera is not None and self.camera.error is not None:
                break  # a broken stream delivers nothing more
            world_done = self.world is None or self._world_t_us() + self.world.origin_us >= end_host_ns // NS_PER_US
            if world_done and self._camera_reached_ns() >= end_host_ns:
                break
            now = (self.last_camera_device_us, self._world_progress())
            if now != seen:
                last_progress, seen = time.monotonic(), now
            elif time.monotonic() - last_progress > stall_s:
                break
            time.sleep(0.01)
        behind_us = 0 if self.camera is None else max(0, (end_host_ns - self._camera_reached_ns()) // NS_PER_US)
        with self._lock:
            self._writer = None
        return behind_us

    def _camera_reached_ns(self) -> int:
        """Host time of the newest event delivered (the recording's live camera clock model): a
        chunk's arrival time says nothing when the camera lags (the virtual rig's renderer on a
        loaded host). The arrival time until there is a model."""
        writer = self._writer
        model = writer.clock_model("camera") if writer is not None else None
        if writer is None or model is None or self.last_camera_device_us < 0:
            return self.last_camera_ns
        return writer.t0_host_ns + int(model.to_host_us(self.last_camera_device_us)) * NS_PER_US

    def camera_host_ns(self, t_device_us: int) -> int | None:
        """The host time (ns) of a camera timestamp (device us), through the recording's live camera clock model
        (trigger edges on both clocks); None before a recording has one."""
        writer = self._writer
        model = writer.clock_model("camera") if writer is not None else None
        if writer is None or model is None:
            return None
        return writer.t0_host_ns + int(model.to_host_us(t_device_us)) * NS_PER_US

    def _world_progress(self) -> int:
        return self._world_t_us() if self.world is not None else 0

    def _world_t_us(self) -> int:
        world = self.world
        return int(world.rig_t_us) if hasattr(world, "rig_t_us") else int(world.rig.t_us)

    def tare(self, n_samples: int = 200) -> None:
        """Software-tare the F/T sensor (the indenter free) and zero the monitor."""
        assert self.ft is not None
        offsets = self.ft.tare(n_samples)
        self.tare_n = tuple(float(v) for v in (*offsets.force_n, *offsets.torque_nm))
        self.monitor.set_baseline(np.zeros(3))

    # -- data routing (device threads) ----------------------------------------------------------

    def _hold(self) -> None:
        if self.grbl is not None:
            with contextlib.suppress(Exception):
                self.grbl.feed_hold()

    def _on_ft(self, sample: FtSample) -> None:
        self.monitor.on_sample(sample.t_host_ns, sample.force_n)
        writer = self._writer
        if writer is not None:
            put_ft(writer, sample)
            if self._last_ft_device_us is not None:  # the sensor's 32-bit us counter wraps
                gap_us = (sample.t_device_us - self._last_ft_device_us) & 0xFFFFFFFF
                self.ft_max_gap_us = max(self.ft_max_gap_us, gap_us)
            self._last_ft_device_us = sample.t_device_us
        if self._ft_listeners:
            self._listener_failed(self._ft_listeners.notify(sample))

    def _on_cnc(self, sample: StatusSample) -> None:
        writer = self._writer
        if writer is not None:
            put_cnc(writer, sample)

    def _on_gcode(self, t_host_us: int, direction: int, line: bytes) -> None:
        writer = self._writer
        if writer is not None:
            put_gcode(writer, t_host_us, direction, line)

    def _pump_truth(self) -> None:
        while not self._stop.is_set() and self.world is not None:
            rows = self.world.truth(timeout_s=0.05)
            writer = self._writer
            if rows is not None and writer is not None and "truth/contact" in writer.specs:
                put_truth_rows(writer, rows, self.world.origin_us - writer.t0_host_ns // NS_PER_US)

    def _pump_camera(self) -> None:
        assert self.camera is not None
        while not self._stop.is_set():
            try:
                chunk = self.camera.read(timeout_s=0.05)
            except CameraError:
                return  # camera.error holds it: the runner aborts the recording with it
            if chunk is None:
                if self.camera.ended:
                    return
                continue
            self.last_camera_ns = chunk.t_host_ns
            if chunk.t_device_us >= 0:
                self.last_camera_device_us = chunk.t_device_us
            self.camera_events += int(chunk.events.size)
            writer = self._writer
            if writer is not None:
                put_chunk(writer, chunk)
            if self._listeners:
                self._listener_failed(self._listeners.notify(chunk))
