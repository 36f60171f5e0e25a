"""A headless client of the Foxglove WebSocket protocol: the live view's tests and benchmark connect with it,
subscribe to every channel and count what arrives. It offers both subprotocols, ``foxglove.sdk.v1`` (what
foxglove-sdk's server speaks) and ``foxglove.websocket.v1`` (its predecessor), whose messages are the same.

Protocol (Foxglove's ws-protocol, v1): the server sends JSON text frames (``serverInfo``, ``advertise`` with
its channels: id, topic, encoding, schemaName, schema); the client answers ``subscribe`` with one
subscription id per channel; the server then sends binary frames: opcode 1 (message data), the
subscription id (uint32 LE), the log time (uint64 LE, ns), the message bytes.
"""

from __future__ import annotations

import json
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
MESSAGE_DATA = 0x01


@dataclass
class Received:
    """What one topic brought: arrival times (s, monotonic), log times (ns) and, if kept, the payloads."""

    schema_name: str
    encoding: str
    arrivals_s: list[float] = field(default_factory=list)
    log_times_ns: list[int] = field(default_factory=list)
    payloads: list[bytes] = field(default_factory=list)

    def rate_hz(self) -> float:
        """Messages per second between the first and the last arrival (0 with fewer than two)."""
        if len(self.arrivals_s) < 2:
            return 0.0
        return (len(self.arrivals_s) - 1) / (self.arrivals_s[-1] - self.arrivals_s[0])


class FoxgloveClient:
    """Connect to ``url``, subscribe to every advertised channel and record the messages, in a thread of its own.

    ``keep_payloads``: keep every message's bytes (else only the last of each topic).
    """

    def __init__(self, url: str, *, keep_payloads: bool = False) -> None:
        self.url = url
        self.keep_payloads = keep_payloads
        self.channels: dict[int, dict[str, Any]] = {}
        self.topics: dict[str, Received] = {}
        self.server_info: dict[str, Any] = {}
        self._subscriptions: dict[int, str] = {}
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    def start(self, timeout_s: float = 10.0) -> FoxgloveClient:
        """Connect and wait until the server has advertised its channels and they are subscribed."""
        self._thread = threading.Thread(target=self._run, name="foxglove-client", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s) or self.error is not None:
            raise ConnectionError(f"{self.url}: no channels advertised within {timeout_s} s ({self.error})")
        return self

    def _run(self) -> None:
        from websockets.sync.client import connect

        try:
            with connect(self.url, subprotocols=list(SUBPROTOCOLS), open_timeout=10, max_size=None) as ws:  # type: ignore[arg-type]
                while not self._stop.is_set():
                    try:
                        frame = ws.recv(timeout=0.1)
                    except TimeoutError:
                        continue
                    if isinstance(frame, str):
                        self._on_text(ws, json.loads(frame))
                    else:
                        self._on_binary(frame)
        except Exception as exc:  # the test reads it
            self.error = exc
            self._ready.set()

    def _on_text(self, ws: Any, message: dict[str, Any]) -> None:
        if message.get("op") == "serverInfo":
            self.server_info = message
        elif message.get("op") == "advertise":
            subscriptions = []
            for channel in message["channels"]:
                sub_id = len(self._subscriptions) + 1
                self.channels[int(channel["id"])] = channel
                self._subscriptions[sub_id] = channel["topic"]
                self.topics[channel["topic"]] = Received(channel.get("schemaName", ""), channel.get("encoding", ""))
                subscriptions.append({"id": sub_id, "channelId": int(channel["id"])})
            ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
            self._ready.set()

    def _on_binary(self, frame: bytes) -> None:
        if not frame or frame[0] != MESSAGE_DATA:
            return
        sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
        topic = self._subscriptions.get(sub_id)
        if topic is None:
            return
        received = self.topics[topic]
        received.arrivals_s.append(time.monotonic())
        received.log_times_ns.append(log_time)
        payload = bytes(frame[13:])
        if self.keep_payloads or not received.payloads:
            received.payloads.append(payload)
        else:
            received.payloads[-1] = payload

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def __enter__(self) -> FoxgloveClient:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
