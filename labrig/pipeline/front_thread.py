"""The pipeline's two threads: the front stage in its own thread, the back stage in the caller's.

The front stage (windowing, SAE, tracking) hands its windows to the back stage (depth,
displacements, forces, and whatever the caller does with each result) through a bounded
queue, so window k's forces are computed while window k+1 is tracked; numpy, scipy and
onnxruntime release the GIL in their kernels. :class:`FrontThread` owns that thread, the queue
and the shutdown, the same whether the source is a recording or a live camera:

* the source ends: the front returns, the caller takes what is queued and the iteration stops;
* the caller stops early (breaks, fails, closes its generator): the front is told
  (:attr:`Handoff.halted`), is unblocked if it waits on a full queue, and is joined;
* the front fails: its exception is raised in the caller after the windows queued before it.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator
from types import TracebackType
from typing import Generic, TypeVar

T = TypeVar("T")

#: Seconds between looks at the other side while a queue operation waits (stays responsive to a halt or Ctrl-C).
POLL_S = 0.1


class _End:
    """The front stage has returned (or failed): nothing follows."""


_END = _End()


class Handoff(Generic[T]):
    """The front stage's side of the queue."""

    def __init__(self, items: queue.Queue[T | _End], halted: threading.Event) -> None:
        self._items = items
        self._halted = halted

    @property
    def halted(self) -> bool:
        """The back stage has gone: the front should stop at once."""
        return self._halted.is_set()

    def full(self) -> bool:
        """No room for another item now."""
        return self._items.full()

    def put(self, item: T) -> bool:
        """Queue ``item``, waiting for room; False (dropped) if the back stage goes meanwhile."""
        return _put(self._items, item, self._halted)


def _put(items: queue.Queue[T | _End], item: T | _End, halted: threading.Event) -> bool:
    while not halted.is_set():
        try:
            items.put(item, timeout=POLL_S)
            return True
        except queue.Full:
            continue
    return False


class FrontThread(Generic[T]):
    """Runs ``front(handoff)`` in a thread of its own; iterate to take what it queues, in order.

    >>> with FrontThread(lambda handoff: [handoff.put(k) for k in range(3)], max_queued=2, name="demo") as items:
    ...     list(items)
    [0, 1, 2]

    Use it as a context manager: leaving the block halts the front, empties the queue until the
    thread has ended and joins it; leaving it normally then raises the front's exception, if any.
    """

    def __init__(self, front: Callable[[Handoff[T]], None], *, max_queued: int, name: str) -> None:
        self._items: queue.Queue[T | _End] = queue.Queue(maxsize=max_queued)
        self._halted = threading.Event()
        self._failure: BaseException | None = None
        self._ended = False
        self._front = front
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def _run(self) -> None:
        try:
            self._front(Handoff(self._items, self._halted))
        except BaseException as exc:  # handed to the caller's thread
            self._failure = exc
        finally:
            _put(self._items, _END, self._halted)

    def __enter__(self) -> FrontThread[T]:
        self._thread.start()
        return self

    def __iter__(self) -> Iterator[T]:
        """The queued items in order, waiting for each, until the front has returned."""
        while not self._ended:
            try:
                item = self._items.get(timeout=POLL_S)
            except queue.Empty:
                continue
            if isinstance(item, _End):
                self._ended = True
                return
            yield item

    def queued(self) -> list[T]:
        """Every item queued now, without waiting (the iteration stops after them if the front has returned)."""
        out: list[T] = []
        while not self._ended:
            try:
                item = self._items.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, _End):
                self._ended = True
            else:
                out.append(item)
        return out

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self._halted.set()
        while self._thread.is_alive():  # unblock the front if it waits on a full queue
            try:
                self._items.get_nowait()
            except queue.Empty:
                self._thread.join(0.01)
        self._thread.join()
        if exc_type is None and self._failure is not None:
            raise self._failure
