"""Virtual-rig child processes die with their parent (kill -9 of record or campaign leaves no orphan)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

PARENT = textwrap.dedent("""
    import multiprocessing as mp, os, sys, time
    from labrig.sim.parent_watch import exit_with_parent

    def child(parent_pid, death_signal):
        exit_with_parent(parent_pid, death_signal=death_signal)
        while True:
            time.sleep(0.05)

    if __name__ == "__main__":
        process = mp.get_context("spawn").Process(target=child, args=(os.getpid(), sys.argv[1] == "signal"), daemon=True)
        process.start()
        print(process.pid, flush=True)
        time.sleep(600)
""")


def _alive(pid: int) -> bool:
    """Running (a zombie waiting for its reaper counts as gone)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.add(child)
            todo.append(child)
    return found


def _gone_within(pids: set[int], seconds: float) -> set[int]:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and any(_alive(p) for p in pids):
        time.sleep(0.05)
    return {p for p in pids if _alive(p)}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("how", ["signal", "poll"])
def test_a_child_exits_within_a_second_of_its_parents_kill_9(tmp_path: Path, how: str) -> None:
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    parent = subprocess.Popen([sys.executable, str(script), how], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": os.getcwd()})
    child = 0
    try:
        assert parent.stdout is not None
        child = int(parent.stdout.readline())
        time.sleep(0.5)
        assert _alive(child)
        parent.kill()
        parent.wait()
        assert not _gone_within({child}, 1.5), f"child {child} outlived its parent ({how})"
    finally:
        parent.kill()
        parent.wait()
        if child and _alive(child):
            os.kill(child, signal.SIGKILL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("command", [
    ["record", "--indenter", "sphere"],
    ["campaign", "protocols/demo.toml", "--workers", "2"],
])
def test_kill_9_of_a_command_leaves_no_virtual_rig_process(tmp_path: Path, command: list[str]) -> None:
    """The issue's reproduction: the command is killed while its virtual rig(s) run."""
    command = [*command, "--out", str(tmp_path / "out")]
    proc = subprocess.Popen([sys.executable, "-m", "labrig.cli", *command], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    family: set[int] = set()
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not list(tmp_path.rglob("*.h5.partial")):
            time.sleep(0.1)  # recording: every rig process is up
        assert list(tmp_path.rglob("*.h5.partial")), "the command never started recording"
        family = _descendants(proc.pid)
        assert family, "no child process to watch"
        proc.kill()
        proc.wait()
        left = _gone_within(family, 3.0)
        assert not left, f"orphans after kill -9 of labrig {command[0]}: {sorted(left)}"
    finally:  # whatever the test found, leave nothing of it running
        for pid in {proc.pid, *family}:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.wait()
