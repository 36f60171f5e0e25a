"""The virtual rig served live: its instruments as twins on the host clock.

:class:`LiveWorld` couples the byte-level twins to one :class:`VirtualRig`:

* the GRBL twin (pty) moves the indenter: the rig's tool path is the twin's
  physical tool position at any host time (executed motion, then its plan);
* the Bota twin (pty) measures the rig's wrench at the host time of each
  sample, from the shared :class:`~labrig.sim.contact_track.ContactTrack`
  (microseconds per sample, so it is exact and never late);
* the GRBL output wired to the camera's trigger input (``flood``: M8/M9)
  makes trigger edges on the camera;
* a renderer thread advances the rig's camera behind the host clock by
  ``render_lag_us`` (so its mechanics solves lie in the known past) and hands
  each chunk's events and trigger edges, in camera time, to the EVK4 twin
  (EVT3 on a Unix socket at ``camera_socket``) and/or ``camera_sink``. Events carry their own timestamps, so a renderer
  running late only delays their delivery; the lag is measured.

World time is host microseconds since :meth:`LiveWorld.start`. The gel pose
in ``rig.toml`` is in GRBL's homed frame (limit switches at the travel ends);
the twin powers up with the tool above the gel centre, unhomed (MPos 0 there)
or, with ``homed``, as if homed earlier in the session; its max rates and accelerations
are the rig file's ``[sim.grbl]`` (GRBL's defaults without one).
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from labrig.clock import HostClock, MonotonicClock
from labrig.config import RigConfig
from labrig.indenters import Indenter
from labrig.sim.bota_twin import BotaTwin, BotaTwinParams
from labrig.sim.contact_track import ContactTrack
from labrig.sim.delivery import BurstSchedule
from labrig.sim.evk4_twin import Evk4Twin
from labrig.sim.faults import RigFault
from labrig.sim.grbl_twin import GrblTwin
from labrig.sim.motion import true_gel_in_machine
from labrig.sim.rig import RigOutput, VirtualRig
from labrig.sim.serial_pty import SerialTwin, TwinServer
from labrig.sim.truth_config import sim_config

#: The simulated F/T sensor's clock against the host clock.
FT_CLOCK_ORIGIN_US = 2_000_000_000
FT_CLOCK_DRIFT_PPM = -60.0
#: GIL slice: short enough for the twins to answer promptly, long enough for the renderer.
SWITCH_INTERVAL_S = float(os.environ.get("LABRIG_SWITCH_INTERVAL_S", "0.0005"))
#: Tool clearance above the gel surface at power-on, mm.
POWER_ON_CLEARANCE_MM = 10.0

CameraSink = Callable[[npt.NDArray[np.void], list[tuple[int, int]]], None]


@dataclass
class WorldStats:
    """How the renderer kept up (lag: host time at hand-over minus the chunk's end)."""

    chunks: int = 0
    late_chunks: int = 0
    max_lag_ms: float = 0.0
    events: int = 0
    triggers: int = 0
    sim_s: float = 0.0

    def as_dict(self) -> dict[str, float | int]:
        return {"chunks": self.chunks, "late_chunks": self.late_chunks, "max_lag_ms": round(self.max_lag_ms, 3),
                "events": self.events, "triggers": self.triggers, "sim_s": round(self.sim_s, 3)}


class LiveWorld:
    """GRBL and Bota twins on ptys around one virtual rig; a context manager.

    ``camera_sink(events, triggers)`` receives each rendered chunk (events with
    ``t`` in camera us; trigger edges as (camera us, polarity)); ``None`` skips
    rendering (forces and motion only). ``on_chunk`` sees every
    :class:`RigOutput` (world times), e.g. for an embedded recorder's truth.
    """

    def __init__(
        self,
        rig: RigConfig,
        indenter: Indenter,
        *,
        seed: int = 0,
        clock: HostClock | None = None,
        camera_socket: str | Path | None = None,
        camera_sink: CameraSink | None = None,
        on_chunk: Callable[[RigOutput], None] | None = None,
        trigger_output: str = "flood",
        render_lag_us: int = 30_000,
        chunk_us: int = 10_000,
        grbl_settings: dict[int, float] | None = None,
        bota_params: BotaTwinParams | None = None,
        extra_twins: dict[str, SerialTwin] | None = None,
        homed: bool = False,
    ) -> None:
        self.clock = clock or MonotonicClock()
        self.bursts = BurstSchedule.from_rig(rig, seed)
        self.evk4 = (Evk4Twin(camera_socket, clock=self.clock, release_at=None if self.bursts is None else self._release_at)
                     if camera_socket is not None else None)
        self.camera_sink = camera_sink
        self.on_chunk = on_chunk
        self.trigger_output = trigger_output
        self.render_lag_us = int(render_lag_us)
        self.chunk_us = int(chunk_us)
        # Solves must lie in the past when the renderer asks for them: within the lag.
        self.rig = VirtualRig(rig, indenter, seed=seed, max_solve_interval_us=min(50_000, self.render_lag_us * 2 // 3))
        self.track: ContactTrack = self.rig.bind(self._tool_world)
        # The rig file's [sim.grbl] limits are the twin's EEPROM at power-on; explicit settings win.
        settings = {**sim_config(rig).grbl.settings(), **(grbl_settings or {})}
        self.grbl = GrblTwin(settings, power_on_physical_mm=power_on_tool_mm(rig, indenter), on_output=self._on_output,
                             homed=homed)
        self.bota = BotaTwin(
            bota_params or BotaTwinParams(clock_offset_us=FT_CLOCK_ORIGIN_US, clock_drift_ppm=FT_CLOCK_DRIFT_PPM, seed=seed,
                                          drop_probability=sim_config(rig).ft.drop_probability),
            wrench_at=self._wrench_at,
        )
        # The GRBL twin's port in a relay process: it switches its trigger output when a line
        # arrives, which must not wait on this process's renderer (see labrig.sim.pty_relay).
        relayed = {"grbl"} if isinstance(self.clock, MonotonicClock) else set()
        self.server = TwinServer({"grbl": self.grbl, "bota": self.bota, **(extra_twins or {})}, clock=self.clock,
                                 relayed=relayed)
        self.stats = WorldStats()
        self.error: BaseException | None = None
        self._origin_us: int | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._render_loop, name="labrig-rig", daemon=True)

    # -- lifecycle -------------------------------------------------------------------------------

    @property
    def paths(self) -> dict[str, str]:
        """Device paths by name: serial ports ``grbl``, ``bota``; the ``evk4`` socket if served."""
        paths = dict(self.server.paths)
        if self.evk4 is not None:
            paths["evk4"] = str(self.evk4.path)
        return paths

    def start(self) -> LiveWorld:
        # Short GIL slices: the twins' thread must answer within a fraction of a millisecond.
        sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_S))
        self._origin_us = self.clock.now_ns() // 1000
        self.server.start()
        if self.evk4 is not None:
            self.evk4.start()
        if self.evk4 is not None or self.camera_sink is not None or self.on_chunk is not None:
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        self.server.stop()
        if self.evk4 is not None:
            self.evk4.close()

    def __enter__(self) -> LiveWorld:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def origin_us(self) -> int:
        """Host time (us, the clock's) of world time 0."""
        assert self._origin_us is not None, "the world has not started"
        return self._origin_us

    @property
    def faults(self) -> list[RigFault]:
        """Requests the rig refused while it kept running (a twin's error, a press beyond the gel
        model), by host time; a run that sees one from its own time aborts with it."""
        origin = self._origin_us or 0
        beyond = [RigFault(f.t_host_us + origin, f.message) for f in self.track.kinematics.faults]
        return sorted([*self.server.faults, *beyond], key=lambda f: f.t_host_us)

    def now_world_us(self) -> int:
        assert self._origin_us is not None, "the world has not started"
        return self.clock.now_ns() // 1000 - self._origin_us

    # -- couplings ---------------------------------------------------------------------------------

    def _tool_world(self, t_world_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Physical tool position (N, 3), machine mm (homed frame), at world times."""
        origin = self._origin_us or 0
        t = np.atleast_1d(np.asarray(t_world_us, dtype=np.float64)) + origin
        return self.grbl.position_mm(t) + np.asarray(self.grbl.physical_offset_mm)

    def _wrench_at(self, t_host_us: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        if self._origin_us is None:
            return np.zeros(3), np.zeros(3)
        force, cop, tip = self.track.wrench_state(t_host_us - self._origin_us)
        return self.rig.ft_wrench_of(force, cop, tip)

    def _release_at(self, t_host_us: int) -> int:
        """Host time of the first USB burst at or after ``t_host_us``."""
        assert self.bursts is not None and self._origin_us is not None
        return self._origin_us + self.bursts.release_after(t_host_us - self._origin_us)

    def _on_output(self, t_host_us: int, name: str, level: int) -> None:
        if name == self.trigger_output and self._origin_us is not None:
            self.rig.trigger(t_host_us - self._origin_us, level)

    # -- the renderer --------------------------------------------------------------------------------

    def _render_loop(self) -> None:
        try:
            while not self._stop.is_set():
                # Never past what the twins have served: an output edge (the camera trigger) a
                # starved twin switches late, at its line's arrival, must still lie ahead.
                served = self.server.served_until_us - self.origin_us
                target = min(self.now_world_us() - self.render_lag_us, served)
                ahead = target - self.rig.t_us
                if ahead < self.chunk_us:
                    self._stop.wait(min(self.chunk_us - ahead, self.chunk_us) / 1e6)
                    continue
                t_end = self.rig.t_us + min(ahead, 5 * self.chunk_us)
                out = self.rig.advance(t_end, self._tool_world)
                self._hand_over(out, t_end)
        except BaseException as exc:  # surfaced by the owner (serve prints it)
            self.error = exc
            raise

    def _hand_over(self, out: RigOutput, t_end: int) -> None:
        lag_us = self.now_world_us() - t_end - self.render_lag_us
        s = self.stats
        s.chunks += 1
        s.late_chunks += lag_us > self.chunk_us
        s.max_lag_ms = max(s.max_lag_ms, lag_us / 1000)
        s.events += len(out.events)
        s.triggers += len(out.triggers)
        s.sim_s = t_end / 1e6
        if self.camera_sink is not None or self.evk4 is not None:
            events = out.events.copy()
            events["t"] = self.rig.camera_time_us(out.events["t"])
            triggers = [(int(self.rig.camera_time_us(t)), p) for t, p in out.triggers]
            if self.evk4 is not None:
                self.evk4.feed(events, triggers)
            if self.camera_sink is not None:
                self.camera_sink(events, triggers)
        if self.on_chunk is not None:
            self.on_chunk(out)


def power_on_tool_mm(rig: RigConfig, indenter: Indenter) -> tuple[float, float, float]:
    """Tool reference above the gel centre with POWER_ON_CLEARANCE_MM, in the homed frame."""
    surface = true_gel_in_machine(rig).apply(np.zeros(3))
    tool = surface - np.asarray(indenter.tool_offset_mm) + np.array([0.0, 0.0, POWER_ON_CLEARANCE_MM])
    return (float(tool[0]), float(tool[1]), float(tool[2]))

