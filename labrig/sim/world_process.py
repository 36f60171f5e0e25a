"""The live world in its own process: its own interpreter lock and core, truth sent back.

A recorder that also ran the virtual rig's renderer would share one
interpreter lock with it: the F/T reader and the safety monitor would then
wait behind long simulation steps. :class:`WorldProcess` runs a
:class:`~labrig.sim.world.LiveWorld` in a child process, exactly as
``labrig sim serve`` does, and sends back its device paths, its world-time
origin on the (shared, monotonic) host clock, its renderer's progress and,
per rendered chunk, the truth rows (compact: :func:`~labrig.sim.live.truth_rows`).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import queue
import signal
import threading
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from labrig.config import RigConfig, load_rig
from labrig.errors import LabrigError
from labrig.indenters import DEFAULT_INDENTERS, Indenter, load_indenters
from labrig.physics.grid import network_grid_gel_mm
from labrig.physics.mechanics.tables import table_direction_deg
from labrig.sim.faults import RigFault
from labrig.sim.live import TruthRows, truth_rows
from labrig.sim.parent_watch import exit_with_parent, started_from_main_thread
from labrig.sim.truth_config import true_contact_table
from labrig.sim.world import LiveWorld

#: Truth chunks waiting in the pipe at most (about 10 s of rendering); more are dropped and counted.
TRUTH_QUEUE_CHUNKS = 1000


def prepare_contact_tables(rig: RigConfig, indenter: Indenter, shear_directions_deg: Iterable[float]) -> None:
    """Build (or find cached) the contact tables a non-axisymmetric indenter needs for these shear
    directions (deg, gel frame), before its world starts: a build takes seconds, which the world's
    renderer would otherwise spend mid-run."""
    if indenter.axisymmetric:
        return
    for direction in sorted({table_direction_deg(d) for d in shear_directions_deg}):
        true_contact_table(indenter, rig, direction_deg=direction)


#: How long :meth:`WorldProcess.start` waits for a living world process to serve (s).
START_TIMEOUT_S = 900.0


class WorldProcess:
    """Start with :meth:`start` (or ``with``); :attr:`paths`, :attr:`origin_us`, :meth:`truth`."""

    def __init__(self, rig_path: str | Path, indenter: str, *, indenters_path: str | Path | None = None, seed: int = 0,
                 camera_socket: str | Path, truth: bool = True, homed: bool = True) -> None:
        self.args: dict[str, Any] = {"rig_path": str(rig_path), "indenter": indenter,
                     "indenters_path": None if indenters_path is None else str(indenters_path),
                     "seed": seed, "camera_socket": str(camera_socket), "truth": truth, "homed": homed}
        ctx = mp.get_context("spawn")
        self._ctx = ctx
        self._conn, child_conn = ctx.Pipe()
        self._truth: Any = ctx.Queue(maxsize=TRUTH_QUEUE_CHUNKS)
        self._progress: Any = ctx.Value("q", -1)
        self._stop: Any = ctx.Event()
        self._process = ctx.Process(target=_serve, args=(self.args, child_conn, self._truth, self._progress, self._stop),
                                    name="labrig-world", daemon=True)
        self.paths: dict[str, str] = {}
        self.origin_us = 0
        self.stats: dict[str, Any] = {}
        self.error: str | None = None
        self._faults: list[RigFault] = []
        self._conn_lock = threading.Lock()

    def start(self, timeout_s: float = START_TIMEOUT_S) -> WorldProcess:
        """Start the world's process and wait until it serves (it may first build contact tables, which on a
        busy machine takes minutes): as long as the process lives, up to ``timeout_s``."""
        self.args.update(parent_pid=os.getpid(), death_signal=started_from_main_thread())
        self._process.start()
        waited_s = 0.0
        while not self._conn.poll(1.0):
            waited_s += 1.0
            if not self._process.is_alive():
                code = self._process.exitcode
                self.stop()
                raise LabrigError(f"the virtual rig's process ended while starting (exit code {code}); rerun the "
                                  "command (a campaign resumes where it stopped)")
            if waited_s >= timeout_s:
                self.stop()
                raise LabrigError(f"the virtual rig did not start within {timeout_s:.0f} s: the machine is too busy; "
                                  "close other programs or rerun later (a campaign resumes where it stopped)")
        kind, payload = self._conn.recv()
        if kind == "error":
            self.stop()
            raise LabrigError(f"the virtual rig failed to start: {payload}")
        self.paths, self.origin_us = payload["paths"], payload["origin_us"]
        return self

    @property
    def rig_t_us(self) -> int:
        """World time the renderer has reached (-1 before its first chunk)."""
        return int(self._progress.value)

    def truth(self, timeout_s: float = 0.05) -> TruthRows | None:
        """The next chunk's truth rows (world us), or None if none came within ``timeout_s``."""
        try:
            return self._truth.get(timeout=timeout_s)  # type: ignore[no-any-return]
        except queue.Empty:
            self._poll_messages()
            return None

    @property
    def faults(self) -> list[RigFault]:
        """Requests the rig refused while it kept running (see :attr:`LiveWorld.faults`)."""
        self._poll_messages()
        return list(self._faults)

    def stop(self, timeout_s: float = 10.0) -> None:
        self._stop.set()
        deadline_s = timeout_s
        with contextlib.suppress(EOFError, OSError), self._conn_lock:
            while self._conn.poll(deadline_s):
                kind, payload = self._conn.recv()
                if kind == "stats":
                    self.stats = payload
                    break
                if kind == "error":
                    self.error = payload
                elif kind == "fault":
                    self._faults.append(payload)
        # Drain the queue so the child's feeder thread can exit.
        with contextlib.suppress(Exception):
            while True:
                self._truth.get_nowait()
        self._process.join(timeout_s)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(2)

    def __enter__(self) -> WorldProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _poll_messages(self) -> None:
        with contextlib.suppress(EOFError, OSError), self._conn_lock:
            while self._conn.poll(0):
                kind, payload = self._conn.recv()
                if kind == "error":
                    self.error = payload
                elif kind == "stats":
                    self.stats = payload
                elif kind == "fault":
                    self._faults.append(payload)
        if self.error is None and not self._process.is_alive() and not self._stop.is_set():
            self.error = f"the virtual rig process exited (code {self._process.exitcode})"


def _serve(args: dict[str, Any], conn: Any, truth_queue: Any, progress: Any, stop: Any) -> None:
    """Child process: build the world, report, forward truth until stopped (or the parent is gone)."""
    exit_with_parent(args["parent_pid"], death_signal=args["death_signal"])
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a terminal's Ctrl-C is the parent's to handle: it stops us
    try:
        rig = load_rig(args["rig_path"])
        indenter = load_indenters(args["indenters_path"] or DEFAULT_INDENTERS)[args["indenter"]]
        state: dict[str, Any] = {"dropped": 0}

        def on_chunk(out: Any) -> None:
            if args["truth"]:
                try:
                    truth_queue.put_nowait(truth_rows(out, state["grid"]))
                except queue.Full:
                    state["dropped"] += 1
            progress.value = world.rig.t_us

        world = LiveWorld(rig, indenter, seed=args["seed"], camera_socket=args["camera_socket"], on_chunk=on_chunk,
                          homed=args["homed"])
        state["grid"] = network_grid_gel_mm(rig, world.rig.camera)
        with world:
            conn.send(("ready", {"paths": world.paths, "origin_us": world.origin_us}))
            sent: set[RigFault] = set()
            while not stop.wait(0.1):
                error = world.error or world.server.error
                if error is not None:
                    conn.send(("error", repr(error)))
                    break
                for fault in world.faults:
                    if fault not in sent:
                        sent.add(fault)
                        conn.send(("fault", fault))
        conn.send(("stats", {**world.stats.as_dict(), "truth_chunks_dropped": state["dropped"]}))
    except BaseException as exc:  # reported to the parent, which raises a clear error
        with contextlib.suppress(Exception):
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        truth_queue.cancel_join_thread()
