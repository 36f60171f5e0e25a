"""A child process that exits when its parent is gone, however the parent died.

A virtual rig's child process (its world, a campaign worker) that outlives its parent
(``kill -9``, a crash) would spin on as an orphan, starving everything after it.
:func:`exit_with_parent`, called first thing in the child, makes it go within a second:
on Linux the kernel sends it SIGTERM when the parent dies (``prctl(PR_SET_PDEATHSIG)``), and
on every platform a daemon thread polls the parent pid and ends the process once it changed.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys
import threading
import time

#: How often the fallback thread looks at the parent pid, s.
PARENT_POLL_S = 0.2
#: The exit status of a child whose parent was gone.
PARENT_GONE_EXIT = 75
_PR_SET_PDEATHSIG = 1


def exit_with_parent(parent_pid: int, death_signal: bool = True, poll_s: float = PARENT_POLL_S) -> None:
    """End this process when ``parent_pid`` (the pid of the process that started it) is gone.

    ``death_signal``: also ask Linux for SIGTERM on the parent's death. The kernel sends it when
    the parent *thread* that started this process exits, so pass True only when the parent
    started it from its main thread (which lives as long as the parent). The pid poll always runs.
    """
    if death_signal and sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    if os.getppid() != parent_pid:  # the parent died before the watch was set up
        os._exit(PARENT_GONE_EXIT)
    threading.Thread(target=_watch, args=(parent_pid, poll_s), name="labrig-parent-watch", daemon=True).start()


def started_from_main_thread() -> bool:
    """Whether the calling thread is the process's main thread (see ``death_signal``)."""
    return threading.current_thread() is threading.main_thread()


def _watch(parent_pid: int, poll_s: float) -> None:
    while os.getppid() == parent_pid:
        time.sleep(poll_s)
    os._exit(PARENT_GONE_EXIT)
