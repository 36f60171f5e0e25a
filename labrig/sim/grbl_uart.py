"""The serial side of the GRBL twin: a 328P's UART, its 128-byte RX ring and GRBL's line assembly.

Times are host microseconds (floats). Bytes from the host arrive one per byte time (10 bits)
after the link latency; the twin picks real-time bytes out as they arrive and :meth:`TwinUart.store`
puts the others into the ring, dropping them **silently** when it is full (counted), and losing
them while an EEPROM write keeps the receiver deaf (counted). The main loop drains the ring a
line at a time through GRBL's pre-parser (:meth:`TwinUart.take_line`). Output lines are paced at
the baud rate and leave after the link latency (:meth:`TwinUart.transmit`).
"""

from __future__ import annotations

import math
from collections import deque

from labrig.devices.grbl_protocol import LINE_END, LINE_MAX_CHARS, RX_BUFFER_BYTES


class TwinUart:
    """Bytes in and out of the twin at ``byte_us`` per byte, ``link_latency_us`` each way."""

    def __init__(self, byte_us: float, link_latency_us: float) -> None:
        self.byte_us = byte_us
        self.link_latency_us = link_latency_us
        self.rx_overflow_bytes = 0
        self.rx_blackout_bytes = 0
        self.max_rx_fill_bytes = 0
        self._wire: deque[tuple[float, int]] = deque()
        self._wire_free_us = -math.inf
        self._ring: deque[int] = deque()
        self._deaf_until_us = -math.inf
        self._tx: deque[tuple[float, bytes]] = deque()
        self._tx_free_us = -math.inf
        self._line = bytearray()
        self._in_paren = False
        self._in_comment = False
        self._line_overflow = False

    @property
    def rx_fill_bytes(self) -> int:
        """Bytes waiting in the RX ring."""
        return len(self._ring)

    # -- input ------------------------------------------------------------------------------

    def host_wrote(self, data: bytes, now_us: float) -> None:
        """Bytes the host wrote at ``now_us``: they arrive one per byte time after the latency."""
        start = max(float(now_us) + self.link_latency_us, self._wire_free_us)
        for i, b in enumerate(data):
            self._wire.append((start + (i + 1) * self.byte_us, b))
        if data:
            self._wire_free_us = start + len(data) * self.byte_us

    def next_arrival_us(self) -> float:
        """When the next byte on the wire arrives (inf: none is on its way)."""
        return self._wire[0][0] if self._wire else math.inf

    def arrived(self, t_us: float) -> int | None:
        """The next byte if it has arrived by ``t_us`` and the receiver hears it, else None
        (a byte arriving while the receiver is deaf is lost and counted)."""
        if not self._wire or self._wire[0][0] > t_us:
            return None
        b = self._wire.popleft()[1]
        if t_us < self._deaf_until_us:
            self.rx_blackout_bytes += 1
            return None
        return b

    def deaf_until(self, t_us: float) -> None:
        """An EEPROM write blocks the receive interrupt until ``t_us``."""
        self._deaf_until_us = t_us

    def store(self, b: int) -> None:
        """A byte that is not a real-time command: into the ring, or dropped if the ring is full."""
        if len(self._ring) >= RX_BUFFER_BYTES:
            self.rx_overflow_bytes += 1
        else:
            self._ring.append(b)
            self.max_rx_fill_bytes = max(self.max_rx_fill_bytes, len(self._ring))

    def take_line(self) -> tuple[str, bool] | None:
        """Drain the ring into the line buffer like GRBL's pre-parser: (a complete line, whether
        it overflowed the 79-character buffer), or None while no line is complete."""
        ring = self._ring
        while ring:
            b = ring.popleft()
            if b in (0x0A, 0x0D):
                line, overflow = self._line.decode("ascii"), self._line_overflow
                self._line.clear()
                self._in_paren = self._in_comment = self._line_overflow = False
                return line, overflow
            if self._in_comment:
                continue
            if self._in_paren:
                self._in_paren = b != 0x29
            elif b == 0x28:
                self._in_paren = True
            elif b == 0x3B:
                self._in_comment = True
            elif b <= 0x20 or b >= 0x7F or b == 0x2F:
                continue
            elif len(self._line) >= LINE_MAX_CHARS:
                self._line_overflow = True
            else:
                self._line.append(b - 32 if 0x61 <= b <= 0x7A else b)
        return None

    def clear_input(self) -> None:
        """A reset empties the ring and the line being assembled (bytes still on the wire arrive)."""
        self._ring.clear()
        self._line.clear()
        self._in_paren = self._in_comment = self._line_overflow = False

    # -- output -----------------------------------------------------------------------------

    def send(self, text: str, t_us: float) -> None:
        """Queue a line (``\\r\\n`` added) for sending from ``t_us`` on, after what is queued."""
        data = text.encode("ascii") + LINE_END
        start = max(t_us, self._tx_free_us)
        self._tx.append((start, data))
        self._tx_free_us = start + len(data) * self.byte_us

    def transmit(self, now_us: float) -> bytes:
        """Bytes whose last bit has left the UART by ``now_us`` (less the link latency)."""
        out = bytearray()
        while self._tx:
            start, data = self._tx[0]
            n = int((now_us - self.link_latency_us - start) / self.byte_us + 1e-9)
            if n <= 0:
                break
            if n >= len(data):
                out += data
                self._tx.popleft()
                continue
            out += data[:n]
            self._tx[0] = (start + n * self.byte_us, data[n:])
            break
        return bytes(out)
