"""The live pipeline on a Foxglove WebSocket server (``labrig run --live --view-server``).

Foxglove (or any client of the Foxglove WebSocket protocol: ``foxglove.sdk.v1``) connects to ``ws://HOST:PORT`` and sees
the pipeline's windows as the same ROS 2 messages a result bag holds (:mod:`labrig.pipeline.ros2_messages`:
``/labrig/force_field``, ``/labrig/net_force``, ``/labrig/depth``, ``/labrig/tracks``), and, during a probing run,
every sample of the F/T sensor (its tared reading, sensor axes) on ``/ft_sensor/wrench`` at the sensor's rate (800 Hz),
each stamped with its own time (:meth:`ViewServer.ft_listener`). Channels carry CDR with their ``ros2msg`` schemas,
so Foxglove's 3D, image and plot panels decode them as they would a ROS 2 topic.

The pipeline never waits for the view: :meth:`ViewServer.publish` stamps the window and hands it to the
server's own thread through a short queue; when the view falls behind, the oldest window waiting is dropped
and counted (``windows_skipped``). A depth map goes out when the pipeline made a new one (``--depth-every-ms``
keeps one map for several windows), not again with every window that reuses it. A display needs no more than
``max_rate_hz`` (default 100 Hz): windows closer than that in camera time to the last one sent are thinned out
before they cost the pipeline anything (counted, ``windows_thinned``); at 10 ms windows every one goes out, at 1 ms
one in ten. A window's messages are stamped, and logged, at the host's system clock (``time.time_ns``) when the window
reached the server, as a live ROS 2 node stamps what it publishes.

F/T samples never take a window's place: they wait in a queue of their own (:data:`MAX_PENDING_WRENCHES`, the oldest
pushed out and counted, ``wrenches_skipped``, when the server falls a second behind), and the server's thread sends
what has gathered at least every :data:`WRENCH_FLUSH_S`, one message a sample, with or without windows.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from labrig.clock import HostClock
from labrig.errors import LabrigError
from labrig.pipeline.ros2_messages import TOPIC_TYPES, WindowFields, window_messages
from labrig.pipeline.runtime import WindowResult
from labrig.recording.ros2 import mapping, topics
from labrig.recording.ros2 import messages as M

if TYPE_CHECKING:
    from labrig.devices.bota_stream import FtSample

#: Foxglove's default port.
DEFAULT_PORT = 8765
#: Windows waiting for the server's thread at most; a newer one pushes the oldest out.
QUEUE_WINDOWS = 8
#: The most windows a second the view sends by default: a display's rate, every window of a 10 ms pipeline.
DEFAULT_RATE_HZ = 100.0
#: F/T samples waiting for the server's thread at most: a second of the Bota's 800 Hz; a newer one pushes the oldest out.
MAX_PENDING_WRENCHES = 800
#: The server's thread sends the F/T samples gathered at least this often (s), whether windows come or not.
WRENCH_FLUSH_S = 0.01
#: An F/T sample waiting to be sent: (stamp ns on the system clock, force N, torque N m; sensor axes).
PendingWrench = tuple[int, npt.ArrayLike, npt.ArrayLike]


@dataclass(frozen=True)
class ViewServerStats:
    """What the server did: windows sent, windows dropped because it fell behind, windows thinned to its rate, F/T
    samples sent, F/T samples dropped because it fell behind."""

    url: str
    windows_published: int
    windows_skipped: int
    wrenches_published: int
    windows_thinned: int = 0
    max_rate_hz: float = DEFAULT_RATE_HZ
    wrenches_skipped: int = 0


class ViewServer:
    """A Foxglove WebSocket server for one live run; use as a context manager.

    ``rest_mm``: the markers' rest points (M, 3), gel frame, mm (the force field's places are rest +
    displacement). ``port`` 0 takes a free port (:attr:`port` tells which). ``max_rate_hz``: the most windows a
    second sent (camera time; 0: every window).
    """

    def __init__(self, rest_mm: npt.ArrayLike, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 name: str = "labrig", max_rate_hz: float = DEFAULT_RATE_HZ) -> None:
        if not (max_rate_hz >= 0):
            raise LabrigError(f"the view's rate must be zero (every window) or positive (Hz), not {max_rate_hz}")
        self.max_rate_hz = float(max_rate_hz)
        self._min_spacing_us = 1e6 / max_rate_hz if max_rate_hz > 0 else 0.0
        self._last_sent_t1_us: int | None = None
        self.windows_thinned = 0
        self.rest_mm = np.asarray(rest_mm, np.float64)
        self.host, self.requested_port, self.name = host, int(port), name
        self._queue: queue.Queue[tuple[str, int, Any]] = queue.Queue(maxsize=QUEUE_WINDOWS)
        self._server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}
        self._types = {**TOPIC_TYPES, topics.WRENCH: M.WRENCH_STAMPED}
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._wrenches: deque[PendingWrench] = deque()  # guarded by _lock
        self.windows_published = self.windows_skipped = self.wrenches_published = self.wrenches_skipped = 0

    def start(self) -> ViewServer:
        """Open the server and its channels (one line if foxglove-sdk is missing or the port is taken)."""
        try:
            import foxglove
        except ImportError:
            raise LabrigError(f"the live view server needs the foxglove-sdk package: {M.INSTALL_HINT}") from None
        store = M.typestore()
        context = self._context = foxglove.Context()  # kept: the channels close with their context
        for topic, msgtype in self._types.items():
            schema = foxglove.Schema(name=msgtype, encoding="ros2msg", data=store.generate_msgdef(msgtype)[0].encode())
            self._channels[topic] = foxglove.Channel(topic, schema=schema, message_encoding="cdr", context=context)
        try:
            self._server = foxglove.start_server(name=self.name, host=self.host, port=self.requested_port, context=context)
        except Exception as exc:  # the SDK raises its own error types; any of them means no server
            raise LabrigError(f"cannot serve the live view on {self.host}:{self.requested_port} ({exc}); "
                              "give another --view-port (0: any free one)") from None
        self._thread = threading.Thread(target=self._run, name="labrig-view-server", daemon=True)
        self._thread.start()
        return self

    @property
    def port(self) -> int:
        return int(self._server.port) if self._server is not None else self.requested_port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def __enter__(self) -> ViewServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the pipeline's side: never blocks ------------------------------------------------------------

    def publish(self, r: WindowResult) -> None:
        """Hand one window to the server (its arrays are the pipeline's own and are not changed afterwards), unless
        it is closer to the last one sent than the view's rate allows."""
        last = self._last_sent_t1_us
        if last is not None and r.t1_us - last < self._min_spacing_us:
            self.windows_thinned += 1
            return
        self._last_sent_t1_us = r.t1_us
        self._offer(("window", time.time_ns(), r))

    def publish_wrench(self, force_n: npt.ArrayLike, torque_nm: npt.ArrayLike = (0.0, 0.0, 0.0), *,
                       t_ns: int | None = None) -> None:
        """Hand one F/T reading (N, N m; the sensor's axes) to the server, stamped ``t_ns`` (ns, the system clock,
        ``time.time_ns``; None: now). Never blocks: a second's samples wait at most, the oldest pushed out."""
        item = (time.time_ns() if t_ns is None else int(t_ns), force_n, torque_nm)
        with self._lock:
            if len(self._wrenches) >= MAX_PENDING_WRENCHES:
                self._wrenches.popleft()
                self.wrenches_skipped += 1
            self._wrenches.append(item)

    def ft_listener(self, clock: HostClock) -> Callable[[FtSample], None]:
        """A listener for :meth:`~labrig.protocol.session.RigSession.add_ft_listener` that sends every F/T sample, each
        stamped with its own host time (its ``t_host_ns`` on ``clock``) moved to the system clock the view stamps
        with, by the two clocks' offset taken now."""
        offset_ns = time.time_ns() - clock.now_ns()

        def on_sample(sample: FtSample) -> None:
            self.publish_wrench(sample.force_n, sample.torque_nm, t_ns=sample.t_host_ns + offset_ns)

        return on_sample

    def _offer(self, item: tuple[str, int, Any]) -> None:
        while True:
            try:
                self._queue.put_nowait(item)
                return
            except queue.Full:
                try:
                    dropped = self._queue.get_nowait()
                except queue.Empty:
                    continue
                if dropped[0] == "window":
                    with self._lock:
                        self.windows_skipped += 1

    # -- the server's thread --------------------------------------------------------------------------

    def _run(self) -> None:
        store = M.typestore()
        last_depth: Any = None
        while True:
            try:
                kind, t_ns, payload = self._queue.get(timeout=WRENCH_FLUSH_S)
            except queue.Empty:
                kind, t_ns, payload = "idle", 0, None
            self._send_wrenches(store)
            if kind == "stop":
                return
            if kind == "idle":
                continue
            r: WindowResult = payload
            new_map = r.depth_mm is not last_depth  # the pipeline hands on the same map until depth runs again
            last_depth = r.depth_mm
            fields = WindowFields(t_ns=t_ns, places_mm=self.rest_mm + r.displacement_mm, forces_n=r.forces_n,
                                  net_force_n=r.net_force_n, positions_px=r.positions_px, updated=r.updated,
                                  depth_mm=r.depth_mm if new_map else None)
            for topic, msg in window_messages(store, fields):
                self._log(store, topic, msg, t_ns)
            with self._lock:
                self.windows_published += 1

    def _send_wrenches(self, store: Any) -> None:
        """The F/T samples gathered since the last call, one ``WrenchStamped`` each, stamped and logged at its time."""
        with self._lock:
            batch, self._wrenches = self._wrenches, deque()
        for t_ns, force, torque in batch:
            self._log(store, topics.WRENCH, mapping.wrench_stamped(store, t_ns, topics.FT_FRAME, force, torque), t_ns)
        if batch:
            with self._lock:
                self.wrenches_published += len(batch)

    def _log(self, store: Any, topic: str, msg: Any, t_ns: int) -> None:
        self._channels[topic].log(bytes(store.serialize_cdr(msg, self._types[topic])), log_time=t_ns)

    def stats(self) -> ViewServerStats:
        with self._lock:
            return ViewServerStats(self.url, self.windows_published, self.windows_skipped, self.wrenches_published,
                                   self.windows_thinned, self.max_rate_hz, self.wrenches_skipped)

    def close(self) -> None:
        """Send what is queued (windows and F/T samples), then stop the server."""
        if self._thread is not None:
            while True:
                try:
                    self._queue.put(("stop", 0, None), timeout=1.0)
                    break
                except queue.Full:
                    continue
            self._thread.join()
            self._thread = None
        if self._server is not None:
            self._server.stop()
            self._server = None
