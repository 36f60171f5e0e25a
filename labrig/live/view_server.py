"""The live pipeline on a Foxglove WebSocket server (``labrig run --live --view-server``).

Foxglove (or any client of the Foxglove WebSocket protocol: ``foxglove.sdk.v1``) connects to ``ws://HOST:PORT`` and sees
the pipeline's windows as the same ROS 2 messages a result bag holds (:mod:`labrig.pipeline.ros2_messages`:
``/labrig/force_field``, ``/labrig/net_force``, ``/labrig/depth``, ``/labrig/tracks``), and the F/T
sensor's tared reading on ``/ft_sensor/wrench`` while a probing run reports it. Channels carry CDR with
their ``ros2msg`` schemas, so Foxglove's 3D, image and plot panels decode them as they would a ROS 2 topic.

The pipeline never waits for the view: :meth:`ViewServer.publish` stamps the window and hands it to the
server's own thread through a short queue; when the view falls behind, the oldest window waiting is dropped
and counted (``windows_skipped``). A depth map goes out when the pipeline made a new one (``--depth-every-ms``
keeps one map for several windows), not again with every window that reuses it. A display needs no more than
``max_rate_hz`` (default 100 Hz): windows closer than that in camera time to the last one sent are thinned out
before they cost the pipeline anything (counted, ``windows_thinned``); at 10 ms windows every one goes out, at 1 ms
one in ten. Messages are stamped, and
logged, at the host's system clock (``time.time_ns``) when the window reached the server, as a live ROS 2 node
stamps what it publishes.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.errors import LabrigError
from labrig.pipeline.ros2_messages import TOPIC_TYPES, WindowFields, window_messages
from labrig.pipeline.runtime import WindowResult
from labrig.recording.ros2 import mapping, topics
from labrig.recording.ros2 import messages as M

#: Foxglove's default port.
DEFAULT_PORT = 8765
#: Windows waiting for the server's thread at most; a newer one pushes the oldest out.
QUEUE_WINDOWS = 8
#: The most windows a second the view sends by default: a display's rate, every window of a 10 ms pipeline.
DEFAULT_RATE_HZ = 100.0


@dataclass(frozen=True)
class ViewServerStats:
    """What the server did: windows sent, windows dropped because it fell behind, windows thinned to its rate, F/T
    readings sent."""

    url: str
    windows_published: int
    windows_skipped: int
    wrenches_published: int
    windows_thinned: int = 0
    max_rate_hz: float = DEFAULT_RATE_HZ


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
        self.windows_published = self.windows_skipped = self.wrenches_published = 0

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

    def publish_wrench(self, force_n: npt.ArrayLike, torque_nm: npt.ArrayLike = (0.0, 0.0, 0.0)) -> None:
        """Hand one F/T reading (N, N m; the sensor's axes) to the server."""
        self._offer(("wrench", time.time_ns(), (np.asarray(force_n, np.float64), np.asarray(torque_nm, np.float64))))

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
            kind, t_ns, payload = self._queue.get()
            if kind == "stop":
                return
            if kind == "wrench":
                force, torque = payload
                msg = mapping.wrench_stamped(store, t_ns, topics.FT_FRAME, force, torque)
                self._log(store, topics.WRENCH, msg, t_ns)
                with self._lock:
                    self.wrenches_published += 1
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

    def _log(self, store: Any, topic: str, msg: Any, t_ns: int) -> None:
        self._channels[topic].log(bytes(store.serialize_cdr(msg, self._types[topic])), log_time=t_ns)

    def stats(self) -> ViewServerStats:
        with self._lock:
            return ViewServerStats(self.url, self.windows_published, self.windows_skipped, self.wrenches_published,
                                   self.windows_thinned, self.max_rate_hz)

    def close(self) -> None:
        """Send what is queued, then stop the server."""
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
