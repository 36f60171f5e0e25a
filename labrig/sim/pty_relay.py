"""A twin's serial port in a process of its own: it stamps the host's bytes as they arrive.

A real controller has a processor of its own: it sees the host's bytes when they reach its
UART, whatever the host's load. A twin served from the virtual rig's process shares that
process's interpreter lock with the renderer, and on a loaded host it read a line up to
7 ms after the driver wrote it (measured: the GRBL twin switching its trigger output late),
so the twin acted late although the driver was on time.

This relay holds the pseudo-terminal in a small process that does nothing but wait on it:
when the driver's bytes arrive it stamps them with the host clock (``time.monotonic_ns``)
at once and passes them on, stamped, over a ``SOCK_SEQPACKET`` socket to the twin's server,
which hands the twin the stamp as the bytes' arrival time. Bytes the twin sends go back the
other way and are written to the port. The relay imports only the standard library (it
starts in about 20 ms) and exits when the socket closes, so it never outlives its server.

Messages to the server: first the port's path (UTF-8), then per read an 8-byte little-endian
host time (ns) followed by the bytes. Messages from the server: bytes to write.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
import struct
import sys
import time
import tty

STAMP = struct.Struct("<q")
#: Largest read from the pty per message, bytes.
READ_BYTES = 4096


def relay(sock: socket.socket) -> None:
    """Open a pty, send its path, relay until ``sock`` closes."""
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    sock.send(os.ttyname(slave).encode())
    watched: list[int | socket.socket] = [master, sock]
    while True:
        readable, _, _ = select.select(watched, [], [])
        stamp_ns = time.monotonic_ns()
        if master in readable:
            data = _read(master)
            if data:
                sock.send(STAMP.pack(stamp_ns) + data)
        if sock in readable:
            out = sock.recv(1 << 16)
            if not out:
                return
            _write(master, out)


def _read(master: int) -> bytes:
    try:
        return os.read(master, READ_BYTES)
    except BlockingIOError:
        return b""
    except OSError as exc:  # EIO: no client has the port open
        if exc.errno == errno.EIO:
            time.sleep(0.001)  # the master stays readable (hung up) until a client opens the port
            return b""
        raise


def _write(master: int, data: bytes) -> None:
    """What the pty takes now; the rest is lost, as a real port's output when nobody reads it."""
    with contextlib.suppress(BlockingIOError, OSError):
        os.write(master, data)


if __name__ == "__main__":
    with socket.socket(fileno=int(sys.argv[1])) as parent:
        with contextlib.suppress(BrokenPipeError, ConnectionResetError, KeyboardInterrupt):
            relay(parent)
