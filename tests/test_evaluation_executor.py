"""run_tasks: in-process and process-pool runs, the result cache, failures, progress, the Dask import guard.

The Dask cluster path and the pool on the real tracking task are in test_evaluation_tracking.py.
"""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labrig.errors import LabrigError
from labrig.executor import TasksFailed, run_tasks, task_inputs
from labrig.result_cache import ResultCache, file_fingerprint


def summarise_file(task: dict[str, Any]) -> dict[str, Any]:
    """A cheap task: statistics of a file's bytes, in every shape a result may take."""
    if task.get("fail"):
        raise ValueError(f"asked to fail on {Path(task['path']).name}")
    data = np.frombuffer(Path(task["path"]).read_bytes(), np.uint8)
    return {"n_bytes": int(data.size), "mean": float(data.mean()) * task["scale"], "histogram": np.bincount(data, minlength=256),
            "halves": [data[: data.size // 2].astype(np.float32), {"name": Path(task["path"]).name, "none": None}],
            "flag": True}


summarise_file.cache_version = "1"  # type: ignore[attr-defined]


@dataclass(frozen=True)
class FileTask:
    path: str
    scale: float = 1.0


def summarise_file_task(task: FileTask) -> dict[str, Any]:
    return summarise_file({"path": task.path, "scale": task.scale})


@dataclass(frozen=True)
class Part:
    name: str
    values: np.ndarray


@dataclass(frozen=True)
class FileSummary:
    n_bytes: int
    histogram: np.ndarray
    shape: tuple[int, int]
    parts: list[Part]
    by_name: dict[str, Part]
    note: str | None = None


def summary_of_file(task: FileTask) -> FileSummary:
    """A task whose result is a frozen dataclass holding arrays, a tuple, and lists and dicts of dataclasses."""
    data = np.frombuffer(Path(task.path).read_bytes(), np.uint8)
    half = Part("half", data[: data.size // 2].astype(np.float32))
    return FileSummary(int(data.size), np.bincount(data, minlength=256), (2, 3), [half], {"half": half})


def assert_same(a: Any, b: Any) -> None:
    """Equal plain results: arrays by value and dtype, the rest by ==."""
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys()
        for k in a:
            assert_same(a[k], b[k])
    elif isinstance(a, list | tuple):
        assert isinstance(b, list) and len(a) == len(b)
        for x, y in zip(a, b):
            assert_same(x, y)
    else:
        assert a == b


@pytest.fixture()
def files(tmp_path: Path) -> list[Path]:
    rng = np.random.default_rng(0)
    paths = []
    for k, size in enumerate((1000, 50_000, 3_000_000)):  # the last is sampled, not read whole, by the fingerprint
        path = tmp_path / f"f{k}.bin"
        path.write_bytes(rng.integers(0, 256, size, dtype=np.uint8).tobytes())
        paths.append(path)
    return paths


def test_cache_round_trip_hits_and_misses(tmp_path: Path, files: list[Path]) -> None:
    tasks = [{"path": str(p), "scale": 2.0} for p in files]
    seen: list[tuple[int, int]] = []
    first = run_tasks(summarise_file, tasks, workers=1, cache_dir=tmp_path / "cache", progress=lambda d, n: seen.append((d, n)))
    assert (first.hits, first.misses, first.failures) == (0, 3, [])
    assert seen[0] == (0, 3) and seen[-1] == (3, 3) and [d for d, _ in seen] == sorted(d for d, _ in seen)
    second = run_tasks(summarise_file, tasks, workers=1, cache_dir=tmp_path / "cache")
    assert (second.hits, second.misses) == (3, 0)
    assert "3 cached, 0 computed" in second.summary()
    for a, b in zip(first, second):
        assert_same(a, b)
    assert first[0]["halves"][1] == {"name": "f0.bin", "none": None}

    # A touched file (new mtime, same content) misses; so does one rewritten with its old size and mtime restored.
    stat = files[1].stat()
    os.utime(files[1], ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    data = bytearray(files[2].read_bytes())
    stat2 = files[2].stat()
    data[0] ^= 0xFF
    files[2].write_bytes(bytes(data))
    os.utime(files[2], ns=(stat2.st_atime_ns, stat2.st_mtime_ns))
    third = run_tasks(summarise_file, tasks, workers=1, cache_dir=tmp_path / "cache")
    assert (third.hits, third.misses) == (1, 2)
    assert third[2]["histogram"].sum() == 3_000_000 and not np.array_equal(third[2]["histogram"], first[2]["histogram"])

    # Other inputs, another version of the function, or no cache at all: computed again.
    assert run_tasks(summarise_file, [{**tasks[0], "scale": 3.0}], workers=1, cache_dir=tmp_path / "cache").misses == 1
    assert run_tasks(summarise_file, tasks, workers=1, cache_dir=tmp_path / "cache", use_cache=False).misses == 3


def test_a_networks_card_is_part_of_its_key(tmp_path: Path) -> None:
    """A depth network is its .onnx and the card beside it: a card edited (another integrator setting) is a miss."""
    onnx, card = tmp_path / "net.onnx", tmp_path / "net.json"
    onnx.write_bytes(b"weights")
    card.write_text('{"inputs": {"brightness": {"tau_s": 3600.0}}}')
    cache = ResultCache(tmp_path / "cache", summarise_file)
    before = cache.key({"model": str(onnx)})
    assert cache.key({"model": str(onnx)}) == before
    stat = card.stat()
    card.write_text('{"inputs": {"brightness": {"tau_s": 36000.0}}}')
    os.utime(card, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert cache.key({"model": str(onnx)}) != before


def test_cache_version_and_dataclass_tasks(tmp_path: Path, files: list[Path], monkeypatch: pytest.MonkeyPatch) -> None:
    tasks = [FileTask(str(p)) for p in files[:2]]
    assert run_tasks(summarise_file_task, tasks, workers=1, cache_dir=tmp_path).misses == 2
    assert run_tasks(summarise_file_task, tasks, workers=1, cache_dir=tmp_path).hits == 2
    monkeypatch.setattr(summarise_file_task, "cache_version", "2", raising=False)
    assert run_tasks(summarise_file_task, tasks, workers=1, cache_dir=tmp_path).misses == 2


def test_dataclass_results_come_back_from_the_cache_and_the_pool(tmp_path: Path, files: list[Path]) -> None:
    tasks = [FileTask(str(p)) for p in files[:2]]
    computed = run_tasks(summary_of_file, tasks, workers=2, cache_dir=tmp_path)
    cached = run_tasks(summary_of_file, tasks, workers=1, cache_dir=tmp_path)
    assert (computed.misses, cached.hits) == (2, 2)
    for a, b in zip(computed, cached):
        assert isinstance(b, FileSummary) and isinstance(b.parts[0], Part) and isinstance(b.by_name["half"], Part)
        assert b.shape == (2, 3) and b.n_bytes == a.n_bytes and b.note is None
        assert_same(a.histogram, b.histogram)
        assert_same(a.parts[0].values, b.parts[0].values)


def test_corrupt_or_partial_entries_are_misses(tmp_path: Path, files: list[Path]) -> None:
    task = {"path": str(files[0]), "scale": 1.0}
    first = run_tasks(summarise_file, [task], workers=1, cache_dir=tmp_path)
    cache = ResultCache(tmp_path, summarise_file)
    entry = cache.path(cache.key(task_inputs(task)))
    assert entry.exists() and not list(entry.parent.glob("*.tmp"))  # written through a temporary file, renamed
    entry.write_bytes(entry.read_bytes()[:100])  # as if cut short
    again = run_tasks(summarise_file, [task], workers=1, cache_dir=tmp_path)
    assert again.misses == 1 and again[0]["mean"] == first[0]["mean"]
    assert run_tasks(summarise_file, [task], workers=1, cache_dir=tmp_path).hits == 1


def test_failures_keep_the_other_results_and_name_the_task(tmp_path: Path, files: list[Path]) -> None:
    tasks = [{"path": str(p), "scale": 1.0, "fail": k == 1} for k, p in enumerate(files)]
    with pytest.raises(TasksFailed) as caught:
        run_tasks(summarise_file, tasks, workers=1, cache_dir=tmp_path)
    message = str(caught.value)
    assert "1 of 3 tasks failed" in message and "task 1" in message and str(files[1]) in message
    assert "ValueError: asked to fail on f1.bin" in message and "in summarise_file" in message
    results = caught.value.results
    assert results[1] is None and results[0]["n_bytes"] == 1000 and results[2]["n_bytes"] == 3_000_000
    assert isinstance(caught.value, LabrigError)
    # The good results were cached; the failed task runs again (and fails again) on the rerun.
    rerun = run_tasks(summarise_file, tasks, workers=1, cache_dir=tmp_path, raise_on_error=False)
    assert (rerun.hits, rerun.misses) == (2, 1)
    assert [f.index for f in rerun.failures] == [1] and rerun.failures[0].task["fail"] is True
    assert "Traceback" in rerun.failures[0].traceback


def test_process_pool_matches_in_process_and_reports_failures(tmp_path: Path, files: list[Path]) -> None:
    tasks = [{"path": str(p), "scale": 0.5, "fail": k == 0} for k, p in enumerate(files)]
    local = run_tasks(summarise_file, tasks, workers=1, use_cache=False, raise_on_error=False)
    pooled = run_tasks(summarise_file, tasks, workers=2, cache_dir=tmp_path, raise_on_error=False)
    assert pooled.misses == 3 and [f.index for f in pooled.failures] == [0]
    assert pooled.failures[0].message == local.failures[0].message == "asked to fail on f0.bin"
    for a, b in zip(local[1:], pooled[1:]):
        assert_same(a, b)
    assert pooled[0] is None


def test_bad_tasks_and_functions_are_refused(tmp_path: Path, files: list[Path]) -> None:
    with pytest.raises(TypeError, match="task input 'path' is a ndarray"):
        run_tasks(summarise_file, [{"path": np.zeros(3)}], workers=1, cache_dir=tmp_path)
    with pytest.raises(LabrigError, match="workers must be at least 1"):
        run_tasks(summarise_file, [{"path": str(files[0])}], workers=0, use_cache=False)
    with pytest.raises(TypeError, match="module-level function"):
        run_tasks(lambda task: {}, [{"a": 1}], workers=2, use_cache=False)
    # A path given as a Path is the same input as its string.
    a = ResultCache(tmp_path, summarise_file).key(task_inputs({"path": files[0]}))
    assert a == ResultCache(tmp_path, summarise_file).key(task_inputs({"path": str(files[0])}))


def test_fingerprint_reads_little_of_a_large_file(files: list[Path]) -> None:
    big = files[2]
    before = file_fingerprint(big)
    assert before.startswith(f"{big.stat().st_size}:") and file_fingerprint(big) == before
    data = bytearray(big.read_bytes())
    data[1_500_000] ^= 0xFF  # between two sampled blocks: not seen; size and mtime catch ordinary rewrites
    stat = big.stat()
    big.write_bytes(bytes(data))
    os.utime(big, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert file_fingerprint(big) == before


def test_scheduler_without_dask_says_what_to_install(monkeypatch: pytest.MonkeyPatch, files: list[Path]) -> None:
    monkeypatch.setitem(sys.modules, "dask.distributed", None)  # import fails as if not installed
    with pytest.raises(LabrigError, match=r"labrig\[eval-dask\]"):
        run_tasks(summarise_file, [{"path": str(files[0]), "scale": 1.0}], scheduler="tcp://127.0.0.1:8786", use_cache=False)


def test_importing_the_evaluation_needs_no_dask() -> None:
    code = ("import sys, labrig, labrig.executor, labrig.evaluation.tracking; "
            "print(any(m == 'dask' or m.startswith(('dask.', 'distributed')) for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
