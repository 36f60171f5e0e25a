"""Where the depth network runs when it is not in the window that needs its map.

**A thread** (:class:`DepthLane`): the forces of every window never wait for the network.

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

**Steps** (:class:`SteppedLane`), for one core: the job is a generator (the network cut into parts,
:meth:`~labrig.pipeline.depthnet.DepthModel.split`, then the map's work) and each window runs one step
of it in its own thread, after its own work. No window carries the whole network, no thread competes
for the core, and the maps a run uses depend only on the stream: a map arrives as many windows after
its own as the job has steps.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Generator
from types import TracebackType
from typing import Generic, TypeVar

import numpy as np
import numpy.typing as npt

DepthJob = Callable[[], npt.NDArray[np.float32]]
T = TypeVar("T")
#: A job in steps: a generator that yields between its steps and returns its result.
Steps = Generator[None, None, T]
DepthSteps = Steps[npt.NDArray[np.float32]]


def one_step(job: Callable[[], T]) -> Steps[T]:
    """``job`` as a job of one step."""
    yield from ()
    return job()


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


class SteppedLane(Generic[T]):
    """Jobs in steps run in the caller's thread, one step per :meth:`step`; one job at a time, a job handed over
    while one runs waits and a newer one replaces it (as :class:`DepthLane`)."""

    def __init__(self) -> None:
        self._running: tuple[Steps[T], int] | None = None
        self._pending: tuple[Steps[T], int] | None = None
        self._done: tuple[T, int] | None = None
        self.submitted = 0
        self.replaced = 0
        self.finished = 0
        self.steps = 0

    def submit(self, job: Steps[T], t1_us: int) -> None:
        """Queue the job of the window ending at ``t1_us`` (a job still waiting is replaced)."""
        if self._pending is not None:
            self._pending[0].close()
            self.replaced += 1
        self._pending = (job, t1_us)
        self.submitted += 1

    def step(self) -> None:
        """One step of the running job (the waiting one starts if none runs); a job's failure is raised here."""
        if self._running is None:
            if self._pending is None:
                return
            self._running, self._pending = self._pending, None
        job, t1_us = self._running
        self.steps += 1
        try:
            next(job)
        except StopIteration as finished:
            self._running = None
            self._done = (finished.value, t1_us)
            self.finished += 1
        except BaseException:
            self._running = None
            raise

    def poll(self) -> tuple[T, int] | None:
        """The newest finished job's result and its window's end (us) since the last poll, else None."""
        done, self._done = self._done, None
        return done

    def close(self) -> None:
        """Drop the running and the waiting job."""
        for held in (self._running, self._pending):
            if held is not None:
                held[0].close()
        self._running = self._pending = None
