"""The live table of ``labrig run --live``, refreshed on stderr while the pipeline streams."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import numpy.typing as npt
from rich import box
from rich.live import Live
from rich.table import Table

from labrig.calibration.ft_frame import ft_on_gel_n
from labrig.cli.console import err_console
from labrig.live.runner import LiveStats
from labrig.pipeline.runtime import WindowResult
from labrig.protocol.runner import RunProgress


class LiveView:
    """The live table: windows, real-time factor, latency, event rate, latest net force (and the
    probing run's phase and F/T force on the gel). Rendered by rich's refresh thread.

    ``ft_to_gel``: the F/T sensor axes in the gel frame (3x3), given when a probing run reports its force.
    """

    def __init__(self, title: str, stats: LiveStats | None, seconds: float | None,
                 ft_to_gel: npt.NDArray[np.float64] | None = None) -> None:
        self.title = title
        self.stats = stats
        self.seconds = seconds
        self.ft_to_gel = ft_to_gel
        self.started = time.monotonic()
        self.load: deque[float] = deque(maxlen=100)  # processing time / window span, recent windows
        self.net_n = np.zeros(3)
        self.progress: RunProgress | None = None
        self._rate = (self.started, 0, 0.0)

    def on_result(self, r: WindowResult) -> None:
        self.load.append(sum(r.seconds.values()) * 1e6 / max(r.t1_us - r.t0_us, 1))
        self.net_n = r.net_force_n

    def on_progress(self, p: RunProgress) -> None:
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
            table.add_column("phase", no_wrap=True)
            table.add_column("F/T on gel N", justify="right", no_wrap=True)
            p = self.progress
            row += [p.phase if p else "starting", _xyz(ft_on_gel_n(p.force_n, self.ft_to_gel)) if p else "-"]
        table.add_row(*row)
        return table


def _xyz(v: npt.ArrayLike) -> str:
    return " ".join(f"{float(x):+6.2f}" for x in np.asarray(v))


@contextmanager
def showing(view: LiveView, enabled: bool) -> Iterator[None]:
    """Keep ``view`` on screen (stderr, 4 refreshes a second) within the block, when ``enabled``."""
    if not enabled:
        yield
        return
    with Live(get_renderable=view.render, console=err_console, refresh_per_second=4, transient=True):
        yield
