"""A recorder process that the crash tests kill or starve of disk space.

Usage: python crash_child.py PATH MODE [FSIZE_LIMIT_BYTES]
MODE: ``run`` records until killed; ``guard`` and ``nospace`` record under a
file-size limit, with the disk-space guard on or off.

Events are deterministic (see :func:`expected_events`) so the parent can check
that what survived is exactly a prefix of what was written. After each commit
the child prints the committed event count, one line, flushed.
"""

from __future__ import annotations

import json
import resource
import signal
import sys
import time

import numpy as np

PACKET_EVENTS = 20_000


def expected_events(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, t_device_us) of the first ``n`` events the child writes."""
    i = np.arange(n, dtype=np.int64)
    return (i * 7919 % 1280).astype(np.uint16), 1_000_000 + i // 20


def main() -> None:
    from labrig.errors import RecordingFault
    from labrig.recording import RecordingWriter
    from labrig.recording.writer import exit_process

    path, mode = sys.argv[1], sys.argv[2]
    if mode in ("guard", "nospace"):
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        limit = int(sys.argv[3])
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    def report(rows: dict[str, int]) -> None:
        print(rows["events"], flush=True)

    writer = RecordingWriter(
        path,
        flush_interval_s=0.1,
        min_free_bytes=(4 << 20) if mode == "guard" else None,
        bulk_codec="none",
        on_commit=report,
    )
    writer.open()
    n = 0
    try:
        while True:
            i = np.arange(n, n + PACKET_EVENTS, dtype=np.int64)
            x, t = expected_events(n + PACKET_EVENTS)
            ok = writer.put_events(x[n:], (i % 720).astype(np.uint16), i % 2, t[n:], int(t[-1]) + 1500)
            writer.put("ft", t_device_us=n // 100, t_host_us=n // 100 + 1200, force_n=[0, 0, -1.0], torque_nm=[0, 0, 0],
                       status=0, temperature_c=30.0)
            n += PACKET_EVENTS
            if writer.fault or not ok:
                break
            time.sleep(0.002 if mode == "run" else 0.0)
    finally:
        try:
            result = writer.close()
            print(json.dumps({"closed": str(result.path), "status": result.exit_status, "reason": result.reason}), flush=True)
        except RecordingFault as exc:
            print(json.dumps({"fault": str(exc)}), flush=True)
    exit_process(0)


if __name__ == "__main__":
    main()
