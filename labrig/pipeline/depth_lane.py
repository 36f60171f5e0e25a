"""The depth network in a thread of its own: the forces of every window never wait for it.

With 1 ms windows and depth every 10 ms, running the network (a few ms) in the back stage holds
up the windows behind it. A :class:`DepthLane` takes the network's job instead: the back stage
prepares the job where the depth source's state lives (the job's inputs are a snapshot, see
:meth:`~labrig.pipeline.depth_sources.DepthSource.depth_job`), hands it over and goes on with the
newest map the lane has finished. One job runs at a time; a job handed over while one runs waits,
and a newer one replaces it (the newest window is the one worth a map). onnxruntime releases the
GIL while the network runs, so on a second core it costs the windows nothing; on one core the
two threads share it and the network's cost is spread over the windows it overlaps.

The maps a run then uses lag by the network's own run time and depend on the scheduling:
:meth:`labrig.pipeline.runtime.Pipeline.run` keeps the lane off unless asked (``depth_lane``),
so that offline results stay reproducible; live runs at 1 kHz use it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from types import TracebackType
from typing import Generic, TypeVar

import numpy as np
import numpy.typing as npt

DepthJob = Callable[[], npt.NDArray[np.float32]]
T = TypeVar("T")


class DepthLane(Generic[T]):
    """One worker thread running depth jobs, newest first; :meth:`poll` returns finished maps in the caller."""

    def __init__(self, name: str = "labrig-depth-lane") -> None:
        self._lock = threading.Condition()
        self._pending: tuple[Callable[[], T], int] | None = None
        self._done: tuple[T, int] | None = None
        self._error: BaseException | None = None
        self._closed = False
        self.submitted = 0
        self.replaced = 0  # jobs dropped for a newer one before they started
        self.finished = 0
        self._thread = threading.Thread(target=self._work, name=name, daemon=True)
        self._thread.start()

    def submit(self, job: Callable[[], T], t1_us: int) -> None:
        """Queue the job of the window ending at ``t1_us`` (a job still waiting is replaced)."""
        with self._lock:
            if self._closed:
                raise RuntimeError("the depth lane is closed")
            if self._pending is not None:
                self.replaced += 1
            self._pending = (job, t1_us)
            self.submitted += 1
            self._lock.notify()

    def poll(self) -> tuple[T, int] | None:
        """The newest finished job's result (a map and what goes with it) and its window's end (us) since the
        last poll, else None; a job's failure is raised here."""
        with self._lock:
            if self._error is not None:
                error, self._error = self._error, None
                raise error
            done, self._done = self._done, None
            return done

    def close(self) -> None:
        """Stop after the running job (a waiting one is dropped) and join the thread."""
        with self._lock:
            self._closed = True
            self._pending = None
            self._lock.notify()
        self._thread.join()

    def __enter__(self) -> DepthLane[T]:
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()

    def _work(self) -> None:
        while True:
            with self._lock:
                while self._pending is None and not self._closed:
                    self._lock.wait()
                if self._closed:
                    return
                assert self._pending is not None
                (job, t1_us), self._pending = self._pending, None
            try:
                depth = job()
            except BaseException as exc:  # handed to the caller by poll()
                with self._lock:
                    self._error = exc
                continue
            with self._lock:
                self._done = (depth, t1_us)
                self.finished += 1
