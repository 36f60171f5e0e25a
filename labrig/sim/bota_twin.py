"""Byte-level twin of a Bota serial F/T sensor, to serve on a pty (:mod:`labrig.sim.serial_pty`).

What it models
--------------
* Boot: at power-on (the first host time it is given) and after ``#``, the
  sensor is deaf for ``boot_delay_us`` (bootloader), then prints its boot text
  (``App Init``, name, S/N, FW version, comm setup), loads the saved
  configuration and streams in RUN mode.
* Config commands (``C R c f b m s l w I #``) with ``r,0,<cmd>,<rc>``
  acknowledgements. Bare letters execute on arrival; commands with arguments
  end on ``\\n``, ``\\r`` or an idle gap of ``idle_gap_us``. Unknown commands get
  rc 1, bad arguments rc 2, config commands in RUN mode rc 3. ``c`` keeps the
  baud code in RAM: a new baud rate takes effect after ``s`` and ``#``. CSV
  output (data format 1) is not modelled (rc 2).
* RUN mode: one 37-byte frame per sample at 51200/S Hz on the device clock,
  queued on a UART paced at the baud rate (10 bits per byte). When the line is
  still busy a sample period later, the sample is skipped and the next frame
  has ``app_took_too_long`` set.
* Measurements: ``wrench_at(t_us)`` (host us; the virtual rig supplies it,
  default zero) plus a bias that drifts with temperature (self-heating towards
  ``ambient + self_heating_c`` with time constant ``warmup_tau_s``), white
  noise, the user calibration matrix (``m`` rows, identity by default) and the
  offsets (``b``). Overrange clips and sets the status bit; ``K=0`` outputs raw
  gauge values with ``raw_measurements`` set.
* Device clock: a uint32 microsecond counter, ``clock_offset_us`` at power-on,
  running ``clock_drift_ppm`` fast against the host clock. It keeps counting
  across ``#`` resets (a real MCU's restarts at 0).

Everything advances on the ``now_us`` it is given (host us); nothing sleeps.
Noise comes from one seeded generator, so a run is reproducible given the same
call times. Fault injection: :meth:`BotaTwin.inject_garbage`,
:meth:`BotaTwin.corrupt_frames`, :meth:`BotaTwin.set_status_bits`,
:meth:`BotaTwin.reset` (a reboot, as on a DTR pulse or a power dip; a pty has
no DTR, so opening it does not reset the twin), and a ``frame_hook`` that may
rewrite each encoded frame.
"""

from __future__ import annotations

import math
import struct
import threading
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from labrig.devices.bota_protocol import (
    BARE_COMMANDS,
    BITS_PER_BYTE,
    FRAME_SIZE,
    MAX_COMMAND_CHARS,
    RC_BAD_ARGUMENTS,
    RC_OK,
    RC_WRONG_MODE,
    TIMESTAMP_MODULUS,
    BootInfo,
    CommandError,
    CommSetup,
    FilterSetup,
    Frame,
    MatrixRow,
    Offsets,
    Status,
    cmd_matrix_row,
    cmd_offsets,
    encode_ack,
    encode_boot_text,
    encode_frame,
    parse_command,
)

Vec3 = tuple[float, float, float]
#: Host time [us] -> (force [N] (3,), torque [N m] (3,)) in the sensor frame.
WrenchSource = Callable[[int], tuple[Iterable[float], Iterable[float]]]
#: Rewrites one encoded frame (37 bytes) before it is queued; may return any bytes.
FrameHook = Callable[[bytes], bytes]
#: A frame's float32 and uint32 fields, for decoding a frame as a receiver would without its bytes.
_FRAME_FIELDS = struct.Struct("<6fIf")

_ZERO3 = np.zeros(3)
#: Samples' normals drawn at a time.
NORMAL_ROWS = 256


def zero_wrench(t_us: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """The default wrench source: no load."""
    return _ZERO3, _ZERO3


@dataclass(frozen=True)
class BotaTwinParams:
    """Everything about the simulated sensor. Units in the names; frames are the sensor frame."""

    name: str = "BotaTwin-Rokubi-Serial"
    serial_number: str = "TW000001"
    firmware_version: str = "1.0.0-twin"
    #: The configuration saved in non-volatile memory at power-on.
    comm: CommSetup = field(default_factory=CommSetup)
    filter: FilterSetup = field(default_factory=FilterSetup)
    offsets: Offsets = field(default_factory=Offsets)
    #: Reset (power-on or ``#``) to boot text (bootloader time).
    boot_delay_us: int = 1_000_000
    #: Command execution to the first byte of its acknowledgement.
    response_delay_us: int = 200
    #: An argument command without terminator ends after this much silence.
    idle_gap_us: int = 50_000
    force_noise_n: float = 0.02
    torque_noise_nm: float = 0.0005
    force_bias_n: Vec3 = (0.35, -0.22, 1.8)
    torque_bias_nm: Vec3 = (0.004, -0.006, 0.002)
    force_bias_n_per_c: Vec3 = (0.02, -0.015, 0.05)
    torque_bias_nm_per_c: Vec3 = (0.0002, 0.0003, -0.0001)
    ambient_c: float = 24.0
    self_heating_c: float = 3.0
    warmup_tau_s: float = 900.0
    temperature_noise_c: float = 0.01
    #: Per-axis measuring range; beyond it the output clips and ``overrange`` is set.
    force_range_n: Vec3 = (500.0, 500.0, 1000.0)
    torque_range_nm: Vec3 = (15.0, 15.0, 15.0)
    #: Device counter [us] at power-on, and how fast it runs against the host clock.
    clock_offset_us: int = 0
    clock_drift_ppm: float = 0.0
    seed: int = 0
    #: The chance that a sample's frame never reaches the host (lost on the link; the device counter goes on).
    drop_probability: float = 0.0


def _boot_info(p: BotaTwinParams) -> BootInfo:
    return BootInfo(True, p.name, p.serial_number, p.firmware_version)


class BotaTwin:
    """The sensor as a :class:`labrig.sim.serial_pty.SerialTwin`. Thread-safe."""

    def __init__(
        self,
        params: BotaTwinParams | None = None,
        wrench_at: WrenchSource | None = None,
        frame_hook: FrameHook | None = None,
    ) -> None:
        self.params = p = params or BotaTwinParams()
        self.wrench_at = wrench_at or zero_wrench
        self.frame_hook = frame_hook
        self._lock = threading.Lock()
        self._rng = np.random.default_rng(p.seed)
        # The generator's normals, drawn NORMAL_ROWS samples ahead (the same stream as one draw per sample).
        self._normal_rows: list[list[float]] = []
        self._normal_next = 0
        self._drop_rng = np.random.default_rng([p.seed, 8])
        self._rate = 1.0 + p.clock_drift_ppm * 1e-6
        self._noise_sigma = np.array([p.force_noise_n] * 3 + [p.torque_noise_nm] * 3)
        self._bias0 = np.array([*p.force_bias_n, *p.torque_bias_nm])
        self._bias_per_c = np.array([*p.force_bias_n_per_c, *p.torque_bias_nm_per_c])
        self._range = np.array([*p.force_range_n, *p.torque_range_nm])
        # The same as Python floats, for the per-sample arithmetic (800 Hz: no small arrays).
        self._noise_sigma_list = self._noise_sigma.tolist()
        self._bias0_list, self._bias_per_c_list = self._bias0.tolist(), self._bias_per_c.tolist()
        self._range_list = self._range.tolist()
        self._smallest_range = min(self._range_list)
        self._identity: bool | None = None
        # Non-volatile and active configuration.
        self._saved = (p.comm, p.filter, p.offsets, np.eye(6))
        self.comm, self.filter, self.offsets, self.matrix = p.comm, p.filter, p.offsets, np.eye(6)
        self._offsets_array: tuple[object, npt.NDArray[np.float64], list[float]] = (None, np.zeros(6), [0.0] * 6)
        self._line_baud_code = p.comm.baud_code
        self._byte_us_of_code: tuple[object, float] = (None, 0.0)
        # Time line.
        self._t0_us: float | None = None  # host time of power-on
        self.mode = "off"  # off -> booting -> run <-> config
        self._boot_done_us = 0.0
        self._next_sample_dev_us = 0.0
        # UART: FIFO of [start_us, data, bytes already returned].
        self._tx: deque[list] = deque()
        # Frames on the line for read_frames (ahead of any bytes in _tx): (start_us, the frame).
        self._whole: deque[tuple[float, Frame]] = deque()
        self._reading_whole = False
        self._line_free_us = 0.0
        # Receiver.
        self._rx = bytearray()
        self._rx_last_us = 0.0
        # Faults and status.
        self._garbage: list[bytes] = []
        self._reset_requested = False
        self._corrupt_left = 0
        self._sticky_status = 0
        self._pending_status = 0
        # What happened, for tests.
        self.commands: list[str] = []
        self.boots = 0
        self.frames_sent = 0
        self.samples_skipped = 0
        #: Frames lost on the link (``drop_probability``).
        self.frames_dropped = 0

    # -- SerialTwin ------------------------------------------------------------

    def receive(self, data: bytes, now_us: int) -> None:
        """Bytes the host wrote, arriving at ``now_us`` (host us)."""
        with self._lock:
            self._whole_to_bytes()
            self._advance(now_us)
            if self.mode == "booting":
                return  # the bootloader ignores what it does not understand
            for byte in data:
                char = chr(byte)
                if char in "\r\n":
                    self._end_command(now_us)
                elif not self._rx and char in BARE_COMMANDS:
                    self._execute(char, now_us)
                    if self.mode == "booting":
                        return
                elif len(self._rx) < MAX_COMMAND_CHARS:
                    self._rx.append(byte)  # beyond the buffer, characters are lost
            self._rx_last_us = now_us

    def transmit(self, now_us: int) -> bytes:
        """Bytes whose last bit has left the UART by ``now_us``."""
        with self._lock:
            self._whole_to_bytes()
            self._advance(now_us)
            out = bytearray()
            byte_us = self._byte_us
            while self._tx:
                chunk = self._tx[0]
                start, data, sent = chunk
                done = min(len(data), math.floor((now_us - start) / byte_us)) if now_us > start else 0
                if done > sent:
                    out += data[sent:done]
                    chunk[2] = done
                if done < len(data):
                    break
                self._tx.popleft()
            return bytes(out)

    def read_frames(self, now_us: int) -> list[Frame] | None:
        """The frames whose last byte has left the UART by ``now_us``, as a receiver decodes them, without
        their bytes: for a host that reads every frame whole and nothing else (virtual time).

        The same frames, at the same reads, as :meth:`transmit` fed to a
        :class:`~labrig.devices.bota_protocol.BotaReceiver` would give. None while the line
        carries or may soon carry anything else (boot text, a command or its answer, injected
        faults, a frame hook, dropped frames): read those with :meth:`transmit`, which sends
        the frames still on the line as bytes first.
        """
        with self._lock:
            if (self.mode != "run" or self._tx or self._rx or self._garbage or self._reset_requested
                    or self._corrupt_left or self.frame_hook is not None or self.params.drop_probability > 0):
                return None
            self._reading_whole = True
            try:
                self._advance(now_us)
            finally:
                self._reading_whole = False
            frames: list[Frame] = []
            whole, byte_us = self._whole, self._byte_us
            while whole and now_us > whole[0][0] and math.floor((now_us - whole[0][0]) / byte_us) >= FRAME_SIZE:
                frames.append(whole.popleft()[1])
            return frames

    def _whole_to_bytes(self) -> None:
        """The frames :meth:`read_frames` left on the line, as bytes ahead of the others."""
        if self._whole:
            self._tx.extendleft([start, encode_frame(frame), 0] for start, frame in reversed(self._whole))
            self._whole.clear()

    # -- fault injection (any thread) ------------------------------------------

    def inject_garbage(self, data: bytes) -> None:
        """Queue ``data`` on the line at the next moment the twin is advanced (between frames)."""
        with self._lock:
            self._garbage.append(bytes(data))

    def corrupt_frames(self, count: int) -> None:
        """Flip one payload byte in each of the next ``count`` frames (header intact, CRC wrong)."""
        with self._lock:
            self._corrupt_left += count

    def reset(self) -> None:
        """Reboot at the next moment the twin is advanced, as a DTR pulse or a power dip would."""
        with self._lock:
            self._reset_requested = True

    def set_status_bits(self, bits: int) -> None:
        """OR ``bits`` into every frame's status from now on (0 clears)."""
        with self._lock:
            self._sticky_status = int(bits)

    # -- introspection -----------------------------------------------------------

    @property
    def line_baud_rate(self) -> int:
        """The baud rate the UART runs at now (set at boot from the saved comm setup)."""
        return CommSetup(baud_code=self._line_baud_code).baud_rate

    def device_us(self, host_us: float) -> float:
        """Device counter (unwrapped) at host time ``host_us``."""
        t0 = self._t0_us if self._t0_us is not None else host_us
        return self.params.clock_offset_us + (host_us - t0) * self._rate

    def host_us_of(self, device_us: float) -> float:
        """Host time at which the (unwrapped) device counter reads ``device_us``."""
        t0 = self._t0_us or 0.0
        return t0 + (device_us - self.params.clock_offset_us) / self._rate

    def temperature_c(self, host_us: float) -> float:
        """Sensor temperature without noise."""
        p = self.params
        age_s = max(0.0, host_us - (self._t0_us or 0.0)) * 1e-6
        return p.ambient_c + p.self_heating_c * (1.0 - math.exp(-age_s / p.warmup_tau_s))

    # -- time line -----------------------------------------------------------------

    @property
    def _byte_us(self) -> float:
        code, byte_us = self._byte_us_of_code
        if code != self._line_baud_code:  # the baud code changes only at a boot: computed once per code
            byte_us = BITS_PER_BYTE * 1e6 / self.line_baud_rate
            self._byte_us_of_code = (self._line_baud_code, byte_us)
        return byte_us

    def _advance(self, now_us: float) -> None:
        """Run every scheduled happening up to ``now_us``, in time order."""
        if self._t0_us is None:
            self._t0_us = float(now_us)
            self._reset(now_us)
        if self._reset_requested:
            self._reset_requested = False
            self._reset(now_us)
        while True:
            t_boot = self._boot_done_us if self.mode == "booting" else math.inf
            t_idle = self._rx_last_us + self.params.idle_gap_us if self._rx and self.mode != "booting" else math.inf
            t_sample = self.host_us_of(self._next_sample_dev_us) if self.mode == "run" else math.inf
            t = min(t_boot, t_idle, t_sample)
            if t > now_us:
                break
            if t == t_boot:
                self._finish_boot(t)
            elif t == t_idle:
                self._end_command(t)
            else:
                self._sample(t)
        for data in self._garbage:
            self._send(now_us, data)
        self._garbage.clear()

    def _send(self, t_us: float, data: bytes) -> None:
        start = max(float(t_us), self._line_free_us)
        self._tx.append([start, data, 0])
        self._line_free_us = start + len(data) * self._byte_us

    def _reset(self, t_us: float) -> None:
        """Reset: the UART stops (unsent bytes are lost) and the bootloader runs."""
        kept: deque[list] = deque()
        if self._tx:
            start, data, sent = self._tx[0]
            done = max(sent, min(len(data), math.floor((t_us - start) / self._byte_us))) if t_us > start else sent
            if done > sent:
                kept.append([start, data[:done], sent])
        self._tx = kept
        self._line_free_us = max(float(t_us), self._line_free_us if kept else 0.0)
        self._rx.clear()
        self.mode = "booting"
        self._boot_done_us = t_us + self.params.boot_delay_us

    def _finish_boot(self, t_us: float) -> None:
        comm, filt, offsets, matrix = self._saved
        self.comm, self.filter, self.offsets, self.matrix = comm, filt, offsets, matrix.copy()
        self._identity = None
        self._line_baud_code = comm.baud_code
        self._line_free_us = max(self._line_free_us, t_us)
        self.boots += 1
        self._send(t_us, encode_boot_text(_boot_info(self.params), comm))
        self._start_run(t_us)

    def _start_run(self, t_us: float) -> None:
        self.mode = "run"
        self._next_sample_dev_us = self.device_us(t_us) + self.filter.period_us

    # -- commands ------------------------------------------------------------------

    def _end_command(self, t_us: float) -> None:
        if self._rx:
            text = self._rx.decode("ascii", errors="replace")
            self._rx.clear()
            self._execute(text, t_us)

    def _ack(self, t_us: float, code: str, rc: int = RC_OK) -> None:
        code = code if code.isascii() and code.isprintable() and code != "," else "?"
        self._send(t_us + self.params.response_delay_us, encode_ack(code, rc))

    def _execute(self, text: str, t_us: float) -> None:
        self.commands.append(text)
        self._identity = None
        try:
            code, args = parse_command(text)
        except CommandError as exc:
            self._ack(t_us, exc.code, exc.rc)
            return
        if self.mode == "run" and code not in "CRI#":
            self._ack(t_us, code, RC_WRONG_MODE)
            return
        if code == "#":
            self._reset(t_us)
            return
        if code in "CI":
            self.mode = "config"
        elif code == "R":
            self._ack(t_us, code)
            if self.mode != "run":
                self._start_run(t_us)
            return
        elif code == "s":
            self._saved = (self.comm, self.filter, self.offsets, self.matrix.copy())
        elif code == "l":
            self.comm, self.filter, self.offsets, matrix = self._saved
            self.matrix = matrix.copy()
        elif code == "w":
            lines = [self.comm.text(), self.filter.text(), cmd_offsets(self.offsets).text]
            lines += [cmd_matrix_row(i, row.tolist()).text for i, row in enumerate(self.matrix)]
            self._send(t_us + self.params.response_delay_us, ("\r\n".join(lines) + "\r\n").encode("ascii"))
        elif isinstance(args, CommSetup):
            if args.data_format != 0:
                self._ack(t_us, code, RC_BAD_ARGUMENTS)  # CSV output is not modelled
                return
            self.comm = args
        elif isinstance(args, FilterSetup):
            self.filter = args
        elif isinstance(args, Offsets):
            self.offsets = args
        elif isinstance(args, MatrixRow):
            self.matrix[args.row] = args.values
        self._ack(t_us, code)

    # -- measurements ------------------------------------------------------------

    def _matrix_is_identity(self) -> bool:
        """Whether the user matrix is the identity (rechecked after every command and boot)."""
        if self._identity is None:
            self._identity = bool(np.array_equal(self.matrix, np.eye(6)))
        return self._identity

    def _offset_values(self) -> npt.NDArray[np.float64]:
        """The active offsets as one (6,) array, rebuilt only when a command replaced them."""
        return self._offsets_now()[0]

    def _offsets_now(self) -> tuple[npt.NDArray[np.float64], list[float]]:
        """The active offsets as an array and as Python floats, rebuilt only when a command replaced them."""
        offsets, values, listed = self._offsets_array
        if offsets is not self.offsets:
            values = np.array([*self.offsets.force_n, *self.offsets.torque_nm])
            listed = values.tolist()
            self._offsets_array = (self.offsets, values, listed)
        return values, listed

    def _normals(self) -> list[float]:
        """The next sample's seven normals: the temperature's, then the six gauges'."""
        if self._normal_next == len(self._normal_rows):
            self._normal_rows = self._rng.standard_normal((NORMAL_ROWS, 7)).tolist()
            self._normal_next = 0
        self._normal_next += 1
        return self._normal_rows[self._normal_next - 1]

    def _sample(self, t_us: float) -> None:
        """One sample at host time ``t_us`` (its device time is ``_next_sample_dev_us``)."""
        device_us = self._next_sample_dev_us
        self._next_sample_dev_us = device_us + self.filter.period_us
        period_host_us = self.filter.period_us / self._rate
        if self._line_free_us - t_us > period_host_us:
            self.samples_skipped += 1  # the loop waited on the UART: this sample is lost
            self._pending_status |= Status.APP_TOOK_TOO_LONG
            return
        p = self.params
        normals = self._normals()
        temperature = self.temperature_c(t_us) + p.temperature_noise_c * normals[0]
        force, torque = self.wrench_at(round(t_us))
        warm = temperature - p.ambient_c
        gauges = [float(load) + bias + per_c * warm for load, bias, per_c in
                  zip((*force, *torque), self._bias0_list, self._bias_per_c_list)]
        status = self._pending_status | self._sticky_status
        self._pending_status = 0
        if max(map(abs, gauges)) > self._smallest_range and any(abs(g) > r for g, r in zip(gauges, self._range_list)):
            status |= Status.OVERRANGE
            gauges = [min(max(g, -r), r) for g, r in zip(gauges, self._range_list)]
        noisy = [g + sigma * n for g, sigma, n in zip(gauges, self._noise_sigma_list, normals[1:])]
        if not self.comm.calibrated:
            v = noisy
            status |= Status.RAW_MEASUREMENTS
        elif self._matrix_is_identity():  # the product's numbers without the product
            v = [n + o for n, o in zip(noisy, self._offsets_now()[1])]
        else:
            v = (self.matrix @ np.array(noisy) + self._offset_values()).tolist()
        if self._reading_whole:  # the fields as the receiver decodes them: float32, 16-bit status
            f = _FRAME_FIELDS.unpack(_FRAME_FIELDS.pack(*v, int(device_us) % TIMESTAMP_MODULUS, temperature))
            frame = Frame(int(status) & 0xFFFF, f[0:3], f[3:6], f[6], f[7])
            start = max(float(t_us), self._line_free_us)
            self._whole.append((start, frame))
            self._line_free_us = start + FRAME_SIZE * self._byte_us
            self.frames_sent += 1
            return
        frame = Frame(int(status), (v[0], v[1], v[2]), (v[3], v[4], v[5]), int(device_us) % TIMESTAMP_MODULUS, temperature)
        data = encode_frame(frame)
        if self._corrupt_left > 0:
            self._corrupt_left -= 1
            flipped = bytearray(data)
            flipped[3 + self.frames_sent % (FRAME_SIZE - 5)] ^= 0x5A
            data = bytes(flipped)
        if self.frame_hook is not None:
            data = self.frame_hook(data)
        if p.drop_probability > 0 and self._drop_rng.random() < p.drop_probability:
            self.frames_dropped += 1
            return
        self.frames_sent += 1
        self._send(t_us, data)
