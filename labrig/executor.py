"""Run one function over many tasks, in parallel, with every result cached on disk (a shared module).

Used by ``labrig evaluate``, ``labrig groundtruth`` and virtual-time campaigns.

:func:`run_tasks` sends ``fn(task)`` for each task through a ``concurrent.futures`` executor:
in this process (``workers=1``), local processes (spawn context, one per core by default), or
a Dask cluster (``scheduler="tcp://host:8786"``, the optional ``eval-dask`` extra). Results
come back in task order.

Contract for ``fn`` and tasks: ``fn`` is a module-level function (picklable by name); a task
is a dict or a frozen dataclass of plain values (str, int, float, bool, None, lists and
nested dicts of them). A result is a frozen dataclass defined at module level (picklable, so
it travels back from worker processes and Dask) of numbers, strings, None, numpy arrays,
lists, and dicts and dataclasses of them; a dict of those works too.

Every result is cached on disk unless ``use_cache=False`` (:class:`labrig.result_cache.ResultCache`,
default folder ``$LABRIG_CACHE/eval``), keyed by the function, its ``cache_version`` attribute, the
task's inputs and the files they name: a rewritten or touched file misses, while an
unchanged one costs a stat and about a megabyte of reading.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

import numpy as np

from labrig.cache import cache_folder
from labrig.errors import LabrigError, SomeInputsFailed
from labrig.result_cache import ResultCache

Task = Mapping[str, Any] | Any  # a dict, or a frozen dataclass instance
ResultT = TypeVar("ResultT")  # what the task function returns: a frozen dataclass (or a dict)
Progress = Callable[[int, int], None]
#: ``run(kind, fn, tasks) -> results``: how the evaluation's planners hand a batch of tasks to :func:`run_tasks`.
Run = Callable[[str, Callable[[Any], Any], list[Any]], list[Any]]

MAX_LISTED_FAILURES = 10  # failures named one by one in a TasksFailed message


class _HasExecutor(Protocol):
    """A dask.distributed ``Client`` (or anything else that hands out a concurrent.futures executor)."""

    def get_executor(self, **kwargs: Any) -> Executor: ...


@dataclasses.dataclass(frozen=True)
class TaskFailure:
    """One task that raised: its position, inputs, the error's type and message, and the full traceback text."""

    index: int
    task: dict[str, Any]
    error: str
    message: str
    traceback: str

    def describe(self) -> str:
        where = _innermost_frame(self.traceback)
        return f"task {self.index} {json.dumps(self.task, default=str)}: {self.error}: {self.message}{where}"


class TaskResults(list[ResultT | None], Generic[ResultT]):
    """Results in task order (None where a task failed), with what the cache did and what failed."""

    def __init__(self, results: Sequence[ResultT | None], *, hits: int, misses: int,
                 failures: Sequence[TaskFailure], seconds: float) -> None:
        super().__init__(results)
        self.hits = hits  # tasks answered from the cache
        self.misses = misses  # tasks computed (including those that failed)
        self.failures = list(failures)
        self.seconds = seconds  # wall time of the whole run, s

    def summary(self) -> str:
        failed = f", {len(self.failures)} failed" if self.failures else ""
        return f"{len(self)} tasks: {self.hits} cached, {self.misses} computed{failed} in {self.seconds:.1f} s"


class TasksFailed(SomeInputsFailed):
    """Some tasks raised; ``results`` holds every result (None for the failed ones), ``failures`` the details."""

    def __init__(self, results: TaskResults[Any]) -> None:
        self.results = results
        self.failures = results.failures
        lines = [f"{len(self.failures)} of {len(results)} tasks failed; the others' results are kept (and cached), "
                 "so after fixing the cause a rerun computes only these:"]
        lines += [f"  {f.describe()}" for f in self.failures[:MAX_LISTED_FAILURES]]
        rest = self.failures[MAX_LISTED_FAILURES:]
        if rest:
            kinds = sorted({f.error for f in rest})
            lines.append(f"  ... and {len(rest)} more ({', '.join(kinds)}); all are in .failures")
        super().__init__("\n".join(lines))


def run_tasks(fn: Callable[[Any], ResultT], tasks: Sequence[Task], *, workers: int | None = None,
              scheduler: str | _HasExecutor | None = None, cache_dir: str | Path | None = None,
              use_cache: bool = True, progress: Progress | None = None,
              raise_on_error: bool = True,
              on_result: Callable[[int, ResultT], None] | None = None) -> TaskResults[ResultT]:
    """``[fn(task) for task in tasks]``, in parallel and cached; see the module docstring.

    ``workers``: local processes (default: one per core); 1 runs in this process, no pool.
    ``scheduler``: a Dask scheduler address (or a ``distributed.Client``); overrides ``workers``.
    ``progress(done, total)`` is called in this thread as tasks finish (cache hits first);
    ``on_result(index, result)`` too, for each task that returned (e.g. to update a manifest
    as results come back rather than at the end).
    A task that raises does not stop the others; with ``raise_on_error`` the run then ends in
    :class:`TasksFailed` (which carries all results), else the failures are in ``.failures``.
    """
    if workers is not None and workers < 1:
        raise LabrigError(f"workers must be at least 1 (1 runs in this process), not {workers}")
    started = time.perf_counter()
    inputs = [task_inputs(task) for task in tasks]
    store = ResultCache(cache_dir or cache_folder("eval"), fn) if use_cache else None
    fingerprints: dict[tuple[str, int, int], str] = {}
    keys = [store.key(item, fingerprints) if store else "" for item in inputs]
    results: list[ResultT | None] = [None] * len(tasks)
    todo = []
    for i, key in enumerate(keys):
        cached = store.load(key) if store else None
        if cached is None:
            todo.append(i)
        else:
            results[i] = cached
            if on_result is not None:
                on_result(i, cached)
    total, done = len(tasks), len(tasks) - len(todo)
    if progress is not None:
        progress(done, total)
    failures: list[TaskFailure] = []

    def finish(i: int, outcome: ResultT | BaseException) -> None:
        nonlocal done
        if isinstance(outcome, BaseException):
            failures.append(_failure(i, inputs[i], outcome))
        else:
            results[i] = outcome
            if store is not None:
                store.save(keys[i], outcome, inputs[i])
            if on_result is not None:
                on_result(i, outcome)
        done += 1
        if progress is not None:
            progress(done, total)

    if todo:
        if scheduler is None and workers == 1:
            for i in todo:
                finish(i, _call(fn, tasks[i]))
        else:
            _run_on_executor(fn, tasks, todo, finish, workers, scheduler)
    failures.sort(key=lambda f: f.index)
    out = TaskResults(results, hits=total - len(todo), misses=len(todo), failures=failures,
                      seconds=time.perf_counter() - started)
    if failures and raise_on_error:
        raise TasksFailed(out)
    return out


def _call(fn: Callable[[Any], ResultT], task: Task) -> ResultT | BaseException:
    try:
        return fn(task)
    except Exception as exc:
        return exc


def _run_on_executor(fn: Callable[[Any], ResultT], tasks: Sequence[Task], todo: list[int],
                     finish: Callable[[int, ResultT | BaseException], None], workers: int | None,
                     scheduler: str | _HasExecutor | None) -> None:
    """Submit the tasks ``todo`` to local processes or a Dask cluster and ``finish`` each as it completes."""
    try:
        pickle.dumps(fn)
    except (pickle.PicklingError, AttributeError, TypeError) as exc:
        raise TypeError(f"{fn!r} cannot be sent to worker processes ({exc}); give a module-level function") from None
    client = None
    if scheduler is None:
        import multiprocessing

        n = max(1, min(workers or os.cpu_count() or 1, len(todo)))
        executor: Executor = ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn"))
    elif isinstance(scheduler, str):
        client = _dask_client(scheduler)
        executor = client.get_executor(pure=False)
    else:
        executor = scheduler.get_executor(pure=False)
    try:
        futures: dict[Future[ResultT], int] = {executor.submit(fn, tasks[i]): i for i in todo}
        for future in as_completed(futures):
            error = future.exception()
            finish(futures[future], error if error is not None else future.result())
    finally:  # everything has finished unless interrupted: then cancel what has not started
        if isinstance(executor, ProcessPoolExecutor):
            executor.shutdown(wait=True, cancel_futures=True)
        else:
            executor.shutdown(wait=False)
        if client is not None:
            client.close()


def _dask_client(address: str) -> Any:
    try:
        from dask.distributed import Client
    except ImportError:
        raise LabrigError(f"--scheduler {address} needs dask.distributed: pip install 'labrig[eval-dask]' "
                          "(or dask[distributed]), or drop --scheduler to use local processes") from None
    try:
        return Client(address, timeout=30)
    except OSError as exc:
        raise LabrigError(f"cannot reach the Dask scheduler at {address} ({exc}); start one with "
                          "`dask scheduler` and `dask worker ADDRESS`, or drop --scheduler") from None


def _failure(index: int, task: dict[str, Any], exc: BaseException) -> TaskFailure:
    text = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    return TaskFailure(index, task, type(exc).__name__, str(exc).splitlines()[0] if str(exc) else "", text)


def _innermost_frame(text: str) -> str:
    """' (at FILE:LINE in FUNC)' of the deepest frame of a traceback's text, '' if none."""
    frames = [line.strip() for line in text.splitlines() if line.strip().startswith('File "')]
    if not frames:
        return ""
    file_part, _, rest = frames[-1].partition(", line ")
    line, _, func = rest.partition(", in ")
    return f" (at {file_part[6:-1]}:{line} in {func})"


# -- task inputs and their files --------------------------------------------------------------------


def task_inputs(task: Task) -> dict[str, Any]:
    """A task's inputs as a plain JSON-able dict (Paths become strings); TypeError for anything else."""
    if dataclasses.is_dataclass(task) and not isinstance(task, type):
        raw: Mapping[str, Any] = {f.name: getattr(task, f.name) for f in dataclasses.fields(task)}
    elif isinstance(task, Mapping):
        raw = task
    else:
        raise TypeError(f"a task must be a dict or a dataclass instance, not {type(task).__name__}")
    return {str(k): _plain_input(v, str(k)) for k, v in raw.items()}


def _plain_input(value: Any, name: str) -> Any:
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, list | tuple):
        return [_plain_input(v, name) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _plain_input(v, name) for k, v in value.items()}
    raise TypeError(f"task input {name!r} is a {type(value).__name__}; tasks hold only paths, numbers, "
                    "strings, bools, None, lists and dicts of them")
