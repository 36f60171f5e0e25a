"""The virtual rig's devices in virtual time: what the drivers would hand a recording, nothing served live.

:class:`OfflineRig` runs the same models as the live world (:mod:`labrig.sim.world`), but on a
:class:`~labrig.clock.ManualClock` that only moves when the caller waits, so a recording takes
as long as the CPU needs and its content never depends on load or wall time:

* GRBL: lines cost their bytes on the wire at the baud rate plus the parse time; motion runs on
  the GRBL planner (:class:`~labrig.devices.motion_profile.MotionTimeline`: trapezoids, junctions,
  jog cancel, feed hold; max rates and accelerations from the rig file's ``[sim.grbl]``); status
  reports are polled at the driver's rate (10 Hz), stamped when
  their last byte arrives, positions printed to 3 decimals; the conversation goes to ``on_gcode``.
* Bota: the byte-level twin (:class:`~labrig.sim.bota_twin.BotaTwin`: noise, temperature-drifting
  bias, its own drifting clock, 800 Hz); the host reads the port every millisecond and stamps the
  frames it finds then; samples are tared as the driver tares. Its boot text goes through the
  driver's receiver; once it streams, frames are read whole (:meth:`BotaTwin.read_frames`: the
  receiver's frames at the same reads, without encoding and decoding their bytes).
* Camera: the rig renders ``render_lag_us`` behind the host clock (its solves in the known past)
  in chunks; each chunk's events and trigger edges, in camera time, arrive at the host time the
  chunk was handed over. The default, ``RENDER_LAG_US``, is the live world's; a run whose loop
  reads the camera renders ``CAMERA_LOOP_RENDER_LAG_US`` behind, so its events arrive about as soon
  as a real camera's would (at the cost of solves three times as often at rest: every 6.7 ms, not 20).

Times: host us = the manual clock's ns // 1000; world time (the rig's) = host us - ``origin_us``,
``PRE_ROLL_US`` after power-on, when the recording starts (:meth:`OfflineRig.power_on`). Machine coordinates: GRBL's homed
frame, as the rig file's gel pose.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.clock import ManualClock
from labrig.config import RigConfig
from labrig.devices.bota_protocol import BotaReceiver, FilterSetup, Frame
from labrig.devices.bota_stream import FtSample
from labrig.devices.camera import EventChunk
from labrig.devices.grbl_protocol import format_number, format_status
from labrig.devices.motion_profile import MachineLimits, MotionTimeline, make_block, quantize_mm
from labrig.devices.raw.stream import TRIGGER_DTYPE
from labrig.indenters import Indenter
from labrig.sim.bota_twin import BotaTwin, BotaTwinParams
from labrig.sim.grbl_settings import initial_settings
from labrig.sim.rig import RigOutput, VirtualRig
from labrig.sim.truth_config import sim_config
from labrig.sim.world import FT_CLOCK_DRIFT_PPM, FT_CLOCK_ORIGIN_US

GRBL_BAUD = 115_200
GRBL_BYTE_US = 10 * 1e6 / GRBL_BAUD
#: GRBL's time from a line's last byte to acting on it, us.
LINE_PARSE_US = 250.0
STATUS_POLL_US = 100_000
#: The host reads the F/T port this often, us.
FT_READ_US = 1_000
#: The renderer's lag behind the host clock and its chunk, us (as the live world).
RENDER_LAG_US = 30_000
#: The lag where a run's loop reads the camera, us: a chunk then arrives at most 20 ms after its
#: first event, near a real EVK4's delivery (milliseconds) rather than the live virtual rig's.
CAMERA_LOOP_RENDER_LAG_US = 10_000
RENDER_CHUNK_US = 10_000
#: The F/T twin's boot time in virtual time, us (it only delays the first samples).
FT_BOOT_US = 50_000
#: Power-on to the recording's start (world time 0), us: the sensor boots, settles and is tared.
PRE_ROLL_US = 500_000
TARE_START_US = 150_000


@dataclass(frozen=True)
class CncStatus:
    """One status report as the driver hands it: host receive time (us), MPos (mm), feed (mm/min), state."""

    t_host_us: int
    position_mm: tuple[float, float, float]
    feed_mm_min: float
    state: str

    def columns(self) -> dict[str, int | float | str | tuple[float, float, float]]:
        return {"t_host_us": self.t_host_us, "position_mm": self.position_mm, "feed_mm_min": self.feed_mm_min,
                "state": self.state}


@dataclass
class OfflineSinks:
    """Where the devices' data goes (host times in us, the clock's); each may be None."""

    ft: Callable[[FtSample], None] | None = None
    cnc: Callable[[CncStatus], None] | None = None
    gcode: Callable[[int, int, bytes], None] | None = None
    camera: Callable[[EventChunk], None] | None = None
    rig_chunk: Callable[[RigOutput], None] | None = None


class OfflineRig:
    """GRBL, Bota and the camera around one :class:`VirtualRig`, stepped by the caller on a manual clock."""

    def __init__(self, rig: RigConfig, indenter: Indenter, *, seed: int, start_tool_mm: npt.ArrayLike,
                 sinks: OfflineSinks, clock: ManualClock | None = None, render_lag_us: int = RENDER_LAG_US) -> None:
        self.clock = clock or ManualClock(1_000_000_000_000)
        self.sinks = sinks
        limits = machine_limits(rig)
        start = quantize_mm(np.asarray(start_tool_mm, dtype=np.float64).tolist(), limits.steps_per_mm)
        self.timeline = MotionTimeline(limits, start, self.now_us)
        self.render_lag_us = int(render_lag_us)
        self.rig = VirtualRig(rig, indenter, seed=seed, max_solve_interval_us=self.render_lag_us * 2 // 3)
        self.track = self.rig.bind(self._tool_world, self._tool_at)
        self.bota = BotaTwin(BotaTwinParams(filter=FilterSetup(sinc_length=64), boot_delay_us=FT_BOOT_US,
                                            clock_offset_us=FT_CLOCK_ORIGIN_US, clock_drift_ppm=FT_CLOCK_DRIFT_PPM,
                                            seed=seed), wrench_at=self._wrench_at)
        self.receiver = BotaReceiver()
        #: Host time (us) of world time 0; the rig's contact track is sampled in world time from power-on.
        self.origin_us = self.now_us + PRE_ROLL_US
        self.rendering = False
        self.tare_n = np.zeros(6)
        self._tare_list = [0.0] * 6
        self.jogging = False
        self.last_status: CncStatus | None = None
        self._next_poll_us = self.now_us
        self._tare_rows: list[tuple[float, ...]] | None = None
        self.bota.transmit(self.now_us)  # power on

    @property
    def now_us(self) -> int:
        return self.clock.now_ns() // 1000

    def power_on(self, tare_samples: int = 200) -> tuple[float, ...]:
        """From power-on to world time 0: the F/T sensor boots and is tared (the indenter free);
        the renderer starts then. Returns the tare (N, N m)."""
        self.dwell(TARE_START_US)
        tare = self.tare(tare_samples)
        self.dwell(self.origin_us - self.now_us)
        self.rendering = True
        return tare

    # -- couplings ----------------------------------------------------------------------------------

    def _tool_world(self, t_world_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        if isinstance(t_world_us, int):  # one time: the contact track's samples, at the F/T rate
            return np.array([self.timeline.position_at(float(t_world_us) + self.origin_us)])
        t = np.atleast_1d(np.asarray(t_world_us, dtype=np.float64)) + self.origin_us
        return self.timeline.positions_at(t)

    def _tool_at(self, t_world_us: int) -> tuple[float, float, float]:
        return self.timeline.position_at(float(t_world_us) + self.origin_us)

    def _wrench_at(self, t_host_us: int) -> tuple[list[float], list[float]]:
        force, cop, tip = self.track.wrench_state(t_host_us - self.origin_us)
        return self.rig.ft_wrench_values(force, cop, tip)

    # -- GRBL ---------------------------------------------------------------------------------------

    def send_line(self, line: str) -> float:
        """The host writes ``line`` now; returns the host time (us) GRBL acts on it (its ``ok`` follows)."""
        t_sent = self.now_us
        t_act = t_sent + (len(line) + 1) * GRBL_BYTE_US + LINE_PARSE_US
        if self.sinks.gcode is not None:
            self.sinks.gcode(t_sent, 0, line.encode())
            self.sinks.gcode(round(t_act + 4 * GRBL_BYTE_US), 1, b"ok")
        return t_act

    def move(self, target_mm: npt.ArrayLike, feed_mm_min: float, *, jog: bool = False) -> float:
        """``G90G53G1`` (or an absolute machine jog) to ``target_mm``; returns when GRBL starts it (host us)."""
        target = quantize_mm(np.asarray(target_mm, dtype=np.float64).tolist(), self.timeline.limits.steps_per_mm)
        words = "".join(f"{a}{format_number(v)}" for a, v in zip("XYZ", target))
        head = "$J=G90G53" if jog else "G90G53G1"
        t_act = self.send_line(f"{head}{words}F{format_number(feed_mm_min)}")
        block = make_block(self.timeline.tail_mm, target, feed_mm_min, self.timeline.limits, tag="jog" if jog else None)
        if block is not None:
            self.timeline.append(block, t_act)
            self.timeline.start(t_act)
            self.jogging = jog
        return t_act

    def jog_cancel(self) -> None:
        """The realtime byte 0x85: decelerate and drop the jog."""
        t_act = self.now_us + GRBL_BYTE_US
        if self.sinks.gcode is not None:
            self.sinks.gcode(self.now_us, 0, b"\x85")
        self.timeline.cancel(max(t_act, self.timeline.t_us))

    def feed_hold(self) -> None:
        """``!``: decelerate to a stop, keep the plan."""
        self.timeline.hold(max(self.now_us + GRBL_BYTE_US, self.timeline.t_us))

    def flush(self) -> None:
        """A soft reset after a hold: the plan is dropped, the position kept."""
        self.timeline.stop(max(self.now_us + GRBL_BYTE_US, self.timeline.t_us))
        self.jogging = False

    def set_output(self, on: bool) -> int:
        """M8/M9: the output wired to the camera's trigger switches; returns the edge's host time (us)."""
        t_edge = round(self.send_line("M8" if on else "M9"))
        self.rig.trigger(t_edge - self.origin_us, int(on))
        return t_edge

    def wait_idle(self, limit_us: int, stop: Callable[[], bool] | None = None) -> CncStatus | None:
        """Step until a status poll reports Idle (None after ``limit_us`` or once ``stop()`` says so)."""
        deadline = self.now_us + limit_us
        while self.now_us < deadline:
            status = self.step()
            if status is not None and status.state == "Idle":
                return status
            if stop is not None and stop():
                return None
        return None

    def dwell(self, duration_us: int, stop: Callable[[], bool] | None = None) -> None:
        end = self.now_us + duration_us
        while self.now_us < end:
            self.step()
            if stop is not None and stop():
                return

    # -- F/T ------------------------------------------------------------------------------------------

    def tare(self, n_samples: int = 200) -> tuple[float, ...]:
        """Average the next ``n_samples`` raw samples (the indenter free) and subtract them from then on."""
        self._tare_rows = []
        while len(self._tare_rows) < n_samples:
            self.step()
        self.tare_n = np.mean(self._tare_rows[:n_samples], axis=0)
        self._tare_list = self.tare_n.tolist()
        self._tare_rows = None
        return tuple(float(v) for v in self.tare_n)

    # -- the clock ------------------------------------------------------------------------------------

    def step(self) -> CncStatus | None:
        """One millisecond on: the F/T port read, a status poll if due, the renderer; returns the poll's report."""
        self.clock.advance_ns(FT_READ_US * 1000)
        now = self.now_us
        frames = self.bota.read_frames(now)
        if frames is None:  # anything but frames on the line: through the driver's receiver
            frames = [event for event in self.receiver.feed(self.bota.transmit(now)) if isinstance(event, Frame)]
        for frame in frames:
            self._on_frame(frame, now)
        status = None
        if now >= self._next_poll_us:
            status = self._poll(now)
            self._next_poll_us = now + STATUS_POLL_US
        if self.rendering:
            self._render(now)
        return status

    def _on_frame(self, frame: Frame, now_us: int) -> None:
        raw = (*frame.force_n, *frame.torque_nm)
        if self._tare_rows is not None:
            self._tare_rows.append(raw)
        if self.sinks.ft is None:
            return
        v = [a - b for a, b in zip(raw, self._tare_list)]
        self.sinks.ft(FtSample(frame.t_device_us, now_us * 1000, (v[0], v[1], v[2]), (v[3], v[4], v[5]), frame.status,
                               frame.temperature_c))

    def _poll(self, now_us: int) -> CncStatus:
        tl = self.timeline
        tl.advance(max(now_us + GRBL_BYTE_US, tl.t_us))
        if tl.state == "idle":
            self.jogging = False
            state = "Idle"
        elif tl.state in ("hold", "held"):
            state = "Hold:0" if tl.state == "held" else "Hold:1"
        else:
            state = "Jog" if self.jogging else "Run"
        position = tuple(round(float(v), 3) for v in tl.position_mm)
        feed = round(tl.speed_mm_s * 60.0)
        text = format_status(state, machine_mm=position, feed_mm_min=feed, spindle_rpm=0.0)
        status = CncStatus(round(tl.t_us + (len(text) + 2) * GRBL_BYTE_US), position, float(feed), state)  # type: ignore[arg-type]
        self.last_status = status
        if self.sinks.cnc is not None:
            self.sinks.cnc(status)
        return status

    def _render(self, now_us: int) -> None:
        target = now_us - self.origin_us - self.render_lag_us
        if target - self.rig.t_us < RENDER_CHUNK_US:
            return
        self.render_to(target)

    def render_to(self, t_world_us: int) -> None:
        """Render the camera up to world time ``t_world_us``; the chunk arrives now."""
        out = self.rig.advance(t_world_us, self._tool_world)
        if self.sinks.camera is not None:
            events = out.events.copy()
            events["t"] = self.rig.camera_time_us(out.events["t"])
            triggers = np.zeros(len(out.triggers), TRIGGER_DTYPE)
            if out.triggers:
                triggers["t"] = self.rig.camera_time_us([t for t, _ in out.triggers])
                triggers["p"] = [p for _, p in out.triggers]
            self.sinks.camera(EventChunk(events, triggers, self.clock.now_ns()))
        if self.sinks.rig_chunk is not None:
            self.sinks.rig_chunk(out)

    def host_ns_of_camera(self, t_camera_us: int) -> int:
        """The host time (ns) of a camera timestamp (us): the inverse of the camera clock's offset and drift."""
        clock = self.rig.truth.camera_clock
        t_world_us = (t_camera_us - clock.origin_us) / (1 + clock.drift_ppm * 1e-6)
        return round((t_world_us + self.origin_us) * 1000)

    def finish(self) -> None:
        """Let the renderer catch up with the host clock (the last events arrive)."""
        if self.rendering:
            end = self.now_us - self.origin_us
            while self.rig.t_us < end:
                self.clock.advance_ns(RENDER_CHUNK_US * 1000)
                self.render_to(min(self.rig.t_us + RENDER_CHUNK_US, end))


def machine_limits(rig: RigConfig) -> MachineLimits:
    """The GRBL planner's limits of the virtual CNC: GRBL's defaults with the rig file's ``[sim.grbl]``."""
    return MachineLimits.from_settings(initial_settings(sim_config(rig).grbl.settings()))
