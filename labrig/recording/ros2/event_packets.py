"""Camera events as ``event_camera_msgs/msg/EventPacket`` payloads, both ways, sans-I/O.

Out: the events of a recording, cut where the recorded USB packets end into messages of a few ms of
host time (as the Metavision driver cuts its messages: it publishes once a buffer arrives more than
its threshold after the last publish), each message's ``events`` the next piece of one EVT 3.0 stream
from labrig's own encoder (:class:`~labrig.devices.raw.Evt3StreamEncoder`), trigger edges included.

In: ``evt3`` payloads decode with labrig's streaming EVT 3.0 decoder, fed one message after another
(the stream's state, its time high and a vector cut by a message's end, carries over); the older
``mono`` and ``trigger`` encodings (event_camera_codecs' ``mono`` and ``trigger`` decoders, one
little-endian 64-bit word per event) decode with numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.devices.raw import TRIGGER_DTYPE, Evt3Decoder, Evt3StreamEncoder
from labrig.errors import LabrigError
from labrig.eventtypes import EVENT_DTYPE

#: The encodings :class:`PacketDecoder` reads.
ENCODINGS = ("evt3", "mono", "trigger")
#: Host time a message gathers recorded packets for before it is published, us (the driver's default
#: message threshold is 1 ms; a few ms keeps a bag's message count low at high event rates).
DEFAULT_PACKET_US = 2000
NS_PER_US = 1000


@dataclass(frozen=True)
class PacketGroup:
    """One message's worth of recorded camera packets.

    ``first_row``/``end_row``: the event rows ``[first_row, end_row)``; ``first_host_us``: the receive
    time of its first packet (the message's header stamp, as the driver stamps it); ``last_host_us``:
    the receive time of its last packet (when the driver publishes it: the bag's log time). Host
    microseconds in the recording's time base.
    """

    first_row: int
    end_row: int
    first_host_us: int
    last_host_us: int


def group_packets(end_row: npt.NDArray[np.int64], t_host_us: npt.NDArray[np.int64],
                  packet_us: int = DEFAULT_PACKET_US) -> list[PacketGroup]:
    """The recorded packets (``event_packets``: each one's end row and receive time) gathered into messages:
    a message is published with the first packet received more than ``packet_us`` after its first one."""
    if packet_us <= 0:
        raise ValueError("packet_us must be positive")
    groups: list[PacketGroup] = []
    start_row, start_host = 0, None
    for row, host in zip(end_row.tolist(), t_host_us.tolist()):
        if row <= start_row:
            continue
        if start_host is None:
            start_host = host
        if host - start_host >= packet_us:
            groups.append(PacketGroup(start_row, row, start_host, host))
            start_row, start_host = row, None
    if start_host is not None:
        groups.append(PacketGroup(start_row, int(end_row[-1]), start_host, int(t_host_us[-1])))
    return groups


class PacketEncoder:
    """Consecutive messages' ``events`` bytes: one EVT 3.0 stream for a sensor of ``width`` x ``height`` px."""

    def __init__(self, width: int, height: int) -> None:
        self._stream = Evt3StreamEncoder(width, height)

    def encode(self, events: npt.NDArray[Any], triggers: npt.NDArray[Any]) -> bytes:
        """The next message's payload: ``events`` (EVENT_DTYPE, sensor time us) and the trigger edges
        (TRIGGER_DTYPE) that fall among them. A :class:`LabrigError` when EVT 3.0 cannot carry them."""
        try:
            return self._stream.encode(events, triggers)
        except ValueError as exc:
            raise LabrigError(f"the events cannot be written as EVT 3.0: {exc}") from None


def decode_mono(payload: bytes, time_base_ns: int) -> npt.NDArray[Any]:
    """``mono`` words (bit 63 polarity, 48-62 y, 32-47 x, 0-31 dt ns) as events, ``t`` in sensor us."""
    words = _words(payload)
    out = np.empty(words.size, EVENT_DTYPE)
    out["p"] = words >> np.uint64(63)
    out["y"] = (words >> np.uint64(48)) & np.uint64(0x7FFF)
    out["x"] = (words >> np.uint64(32)) & np.uint64(0xFFFF)
    out["t"] = (int(time_base_ns) + (words & np.uint64(0xFFFFFFFF)).astype(np.int64)) // NS_PER_US
    return out


def decode_trigger(payload: bytes, time_base_ns: int) -> npt.NDArray[Any]:
    """``trigger`` words (bit 63 edge, 48-62 id, 0-31 dt ns) as trigger edges, ``t`` in sensor us."""
    words = _words(payload)
    out = np.empty(words.size, TRIGGER_DTYPE)
    out["p"] = words >> np.uint64(63)
    out["id"] = (words >> np.uint64(48)) & np.uint64(0x7FFF)
    out["t"] = (int(time_base_ns) + (words & np.uint64(0xFFFFFFFF)).astype(np.int64)) // NS_PER_US
    return out


def _words(payload: bytes) -> npt.NDArray[np.uint64]:
    if len(payload) % 8:
        raise LabrigError(f"a mono/trigger packet holds {len(payload)} bytes, not a whole number of 8-byte words")
    return np.frombuffer(payload, dtype="<u8")


@dataclass(frozen=True)
class DecodedPacket:
    """What one message gave: events (EVENT_DTYPE) and trigger edges (TRIGGER_DTYPE), sensor time in us."""

    events: npt.NDArray[Any]
    triggers: npt.NDArray[Any]


class PacketDecoder:
    """EventPacket messages of one topic, in order, to events and trigger edges.

    The topic's encoding is fixed by its first message; a later message in another one, or big-endian
    words, is one :class:`LabrigError`.
    """

    def __init__(self, topic: str) -> None:
        self.topic = topic
        self.encoding: str | None = None
        self._evt3: Evt3Decoder | None = None
        self.skipped_words = 0

    def decode(self, encoding: str, is_bigendian: bool, time_base: int, payload: bytes,
               width: int, height: int) -> DecodedPacket:
        """One message's fields as the bag holds them (``time_base`` in ns; unused by ``evt3``)."""
        if self.encoding is None:
            if encoding not in ENCODINGS:
                raise LabrigError(f"{self.topic}: event encoding {encoding!r} is not read by labrig; "
                                  f"it reads {', '.join(ENCODINGS)} (the Metavision driver's current one is evt3)")
            self.encoding = encoding
            if encoding == "evt3":
                self._evt3 = Evt3Decoder(width or None, height or None)
        elif encoding != self.encoding:
            raise LabrigError(f"{self.topic}: a packet in {encoding!r} among packets in {self.encoding!r}; "
                              "give a topic of one encoding")
        if is_bigendian:
            raise LabrigError(f"{self.topic}: big-endian event packets are not read; the camera drivers write little-endian")
        no_events, no_triggers = np.zeros(0, EVENT_DTYPE), np.zeros(0, TRIGGER_DTYPE)
        if self._evt3 is not None:
            out = self._evt3.feed(payload)
            return DecodedPacket(out.events, out.triggers)
        if self.encoding == "mono":
            return DecodedPacket(decode_mono(payload, time_base), no_triggers)
        return DecodedPacket(no_events, decode_trigger(payload, time_base))

    def finish(self) -> None:
        """End of the topic: counts the words the evt3 stream could not decode (a partial word at its end included)."""
        if self._evt3 is not None:
            self._evt3.finish()
            self.skipped_words = int(self._evt3.skipped_words)
