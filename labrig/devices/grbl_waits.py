"""Waiting on a GRBL controller: send-response, character-counting streams, fresh status reports,
Idle, banners, with the timeouts that tell a lost ``ok`` from a busy machine.

Everything here runs on the caller's thread over a :class:`~labrig.devices.grbl_channel.GrblChannel`
(whose reader thread moves the tickets along) and every wait has a bound.

A response is late when ``response_timeout_s`` passed since the line was sent *and* since the
last status report that showed the machine busy (Run, Jog, Hold, Home): GRBL legitimately holds
back ``ok`` while its planner is full, while a ``G4``/``M8`` waits for motion to finish, and
during a feed hold. So a lost ``ok`` is reported once the machine is idle (or silent) for that
long; with ``poll_hz=0`` the timeout counts from sending only.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from labrig.devices.grbl_channel import QUERY_TIMEOUT_S, GrblChannel, Reply, StatusSample, Ticket
from labrig.devices.grbl_protocol import GrblAlarm, GrblCommandError, GrblResetError, GrblTimeout, GrblUsageError


@dataclass(frozen=True)
class StreamResult:
    """What :meth:`Grbl.stream` did."""

    mode: str
    lines: int
    t_start_us: int
    t_end_us: int
    max_in_flight_bytes: int

    @property
    def lines_per_s(self) -> float:
        return self.lines / max((self.t_end_us - self.t_start_us) / 1e6, 1e-9)


@dataclass
class _StreamRun:
    """Book-keeping of one :meth:`Grbl.stream` call."""

    total: int
    progress: Callable[[int, int], None] | None
    tickets: list[Ticket] = field(default_factory=list)
    answered: int = 0
    failed: Ticket | None = None
    max_in_flight_bytes: int = 0


class GrblWaits:
    """The caller's side of the conversation with a controller on ``io`` (see the module docstring).

    ``response_timeout_s``: how long a line may go unanswered while the machine is not busy.
    """

    def __init__(self, io: GrblChannel, response_timeout_s: float) -> None:
        self._io = io
        self.response_timeout_s = float(response_timeout_s)

    def _state(self) -> str:
        sample = self._io.last_sample
        return sample.state if sample is not None else "Unknown"

    # -- lines ---------------------------------------------------------------------------------

    def send(self, line: str | bytes, timeout_s: float | None = None) -> Reply:
        """Send one line after every earlier one is answered and wait for its ``ok`` (see :meth:`Grbl.send`)."""
        io = self._io
        data = io.core.check_line(line)
        timeout = self.response_timeout_s if timeout_s is None else float(timeout_s)
        with io.cond:
            while io.core.in_flight:
                self.wait_oldest()
            ticket = io.send_locked(data, timeout)
        io.run_callbacks()
        self.wait_ticket(ticket)
        if ticket.code is not None:
            raise GrblCommandError(ticket.code, ticket.line)
        return Reply(ticket.line, ticket.t_sent_us, ticket.t_answer_us, tuple(ticket.pushed))

    def stream(
        self,
        lines: Iterable[str | bytes],
        *,
        mode: str = "count",
        progress: Callable[[int, int], None] | None = None,
        timeout_s: float | None = None,
    ) -> StreamResult:
        """Send a program, counting characters or line by line, until every line is answered (see :meth:`Grbl.stream`)."""
        if mode not in ("count", "send-response"):
            raise GrblUsageError(f"mode must be 'count' or 'send-response', got {mode!r}")
        io = self._io
        program = [io.core.check_line(line) for line in lines]
        for data in program:
            if re.match(rb"\s*\$\s*(\d|N\d|I=|RST)", data, re.IGNORECASE):
                raise GrblUsageError(f"{data!r} writes EEPROM and must be sent alone: use write_setting() or send()")
        timeout = self.response_timeout_s if timeout_s is None else float(timeout_s)
        run = _StreamRun(len(program), progress)
        t_start = io.now_us()
        with io.cond:
            for i, data in enumerate(program):
                while run.failed is None:
                    self._scan(run)
                    fits = io.core.can_send(data) if mode == "count" else not io.core.in_flight
                    if run.failed is not None or fits:
                        break
                    self.wait_oldest()
                if run.failed is not None:
                    break
                run.tickets.append(io.send_locked(data, timeout, index=i))
                run.max_in_flight_bytes = max(run.max_in_flight_bytes, io.core.in_flight_bytes)
                if io.callbacks_pending or progress is not None:
                    self._scan(run)
            while run.answered < len(run.tickets):
                self._scan(run)
                if run.answered < len(run.tickets):
                    self.wait_step(run.tickets[run.answered])
        io.run_callbacks()
        if run.failed is not None:
            assert run.failed.code is not None
            raise GrblCommandError(run.failed.code, run.failed.line, run.failed.index)
        return StreamResult(mode, len(run.tickets), t_start, io.now_us(), run.max_in_flight_bytes)

    def _scan(self, run: _StreamRun) -> None:
        """Advance over a stream's answered lines (answers come in order): note the first error,
        raise if the controller reset under the stream, report progress, run pending callbacks.
        """
        io = self._io
        tickets = run.tickets
        k = run.answered
        while k < len(tickets) and tickets[k].done:
            if tickets[k].code is not None and run.failed is None:
                run.failed = tickets[k]
            k += 1
        if k < len(tickets) and tickets[k].discarded:
            self.raise_discarded(tickets[k])
        progressed = k != run.answered
        run.answered = k
        if (progressed and run.progress is not None) or io.callbacks_pending:
            io.cond.release()  # callbacks run without the lock
            try:
                io.run_callbacks()
                if progressed and run.progress is not None:
                    run.progress(k, run.total)
            finally:
                io.cond.acquire()

    # -- the controller's state ----------------------------------------------------------------------

    def status(self, timeout_s: float = 1.0) -> StatusSample:
        """A fresh status report, its ``?`` sent after this call began (see :meth:`Grbl.status`)."""
        io = self._io
        t0 = io.now_us()
        deadline = t0 + timeout_s * 1e6
        with io.cond:
            io.request_poll_locked(t0)
            while True:
                io.raise_if_failed()
                sample = io.last_sample
                if sample is not None and sample.t_query_us is not None and sample.t_query_us >= t0:
                    return sample
                if io.core.locked:  # no report will come: say why at once
                    raise GrblAlarm(io.core.alarm or 0, "GRBL answers nothing, not even '?', until soft_reset()")
                now = io.now_us()
                if now >= deadline:
                    raise GrblTimeout(
                        f"no status report within {timeout_s:.1f} s (last state {self._state()}); GRBL does not answer '?' "
                        "while homing: wait for it, else check the port and cable"
                    )
                if io.query_sent_us is None or now - io.query_sent_us > QUERY_TIMEOUT_S * 1e6:
                    io.request_poll_locked(now)
                io.cond.wait(min(0.02, (deadline - now) / 1e6))

    def wait_idle(self, timeout_s: float = 60.0) -> StatusSample:
        """Every line answered and GRBL reporting Idle (see :meth:`Grbl.wait_idle`)."""
        io = self._io
        t0 = io.now_us()
        deadline = t0 + timeout_s * 1e6
        interval_s = 1.0 / io.poll_hz if io.poll_hz > 0 else 0.1
        with io.cond:
            while io.core.in_flight:
                if io.now_us() > deadline:
                    raise GrblTimeout(f"lines still unanswered after {timeout_s:.1f} s")
                self.wait_oldest()
        while True:
            try:
                sample = self.status(timeout_s=max(min(2.0, (deadline - io.now_us()) / 1e6), 0.05))
            except GrblTimeout:  # a report late by seconds (a starved twin) is late, not lost, until the deadline
                if io.now_us() > deadline:
                    raise
                continue
            if sample.report.state == "Idle":
                return sample
            if sample.report.state == "Alarm":
                self.raise_alarm_since(t0, "while waiting for Idle")
                raise GrblAlarm(io.core.alarm or 0, "controller in Alarm while waiting for Idle")
            if io.now_us() > deadline:
                raise GrblTimeout(f"controller still {sample.state} after {timeout_s:.1f} s")
            next_us = min(sample.t_host_us + interval_s * 1e6, deadline)
            with io.cond:  # poll no faster than poll_hz
                while (now := io.now_us()) < next_us:
                    io.raise_if_failed()
                    io.cond.wait((next_us - now) / 1e6)

    def raise_alarm_since(self, t0: int, context: str) -> None:
        """:class:`GrblAlarm` with the latest alarm raised since ``t0`` (us), if any."""
        alarms = self._io.alarms_since(t0)
        if alarms:
            raise GrblAlarm(alarms[-1], context)

    # -- waiting (the lock held unless said) ------------------------------------------------------------

    def wait_step(self, ticket: Ticket | None) -> None:
        """One bounded wait for progress on ``ticket`` (the oldest unanswered line); raises on trouble."""
        self._io.raise_if_failed()
        if ticket is None:
            self._io.cond.wait(0.01)
            return
        if ticket.discarded:
            self.raise_discarded(ticket)
        alarms = self._io.alarms
        if self._io.core.locked and alarms and alarms[-1][0] >= ticket.t_sent_us:
            raise GrblAlarm(alarms[-1][1], f"{ticket.line.decode()!r} unanswered; GRBL ignores all lines until soft_reset()")
        if ticket.done:
            return
        now = self._io.now_us()
        deadline = self._deadline_us(ticket)
        if now >= deadline and not self._awaiting_fresh_status(deadline, now):
            raise self._timeout(ticket, now)
        self._io.cond.wait(min(0.05, max(deadline - now, 10_000) / 1e6))

    def wait_oldest(self) -> None:
        """One bounded wait for progress on the oldest unanswered line."""
        self.wait_step(self._io.tickets[0] if self._io.tickets else None)

    def wait_ticket(self, ticket: Ticket) -> None:
        with self._io.cond:
            while not ticket.done:
                self.wait_step(ticket)
        self._io.run_callbacks()

    def raise_discarded(self, ticket: Ticket) -> None:
        alarms = [code for t, code in self._io.alarms if t >= ticket.t_sent_us]
        if alarms:
            raise GrblAlarm(alarms[-1], f"the controller reset and dropped {ticket.line.decode()!r} unanswered")
        raise GrblResetError(
            f"the controller reset and dropped {ticket.line.decode()!r} unanswered; send it again if still wanted"
        )

    def wait_welcome(self, count: int, timeout_s: float, *, required: bool) -> bool:
        """Wait for banner number ``count + 1``; False (or :class:`GrblTimeout` if ``required``) without it."""
        deadline = self._io.now_us() + timeout_s * 1e6
        with self._io.cond:
            while self._io.welcomes <= count:
                self._io.raise_if_failed()
                now = self._io.now_us()
                if now >= deadline:
                    if required:
                        raise GrblTimeout(
                            f"no GRBL welcome banner within {timeout_s:.1f} s on {self._io.link.name}; "
                            f"is a GRBL controller connected at {self._io.link.baudrate} baud?"
                        )
                    return False
                self._io.cond.wait(min(0.05, (deadline - now) / 1e6))
        return True

    def wait_quiet(self, quiet_s: float, max_s: float) -> None:
        """Wait until nothing arrived for ``quiet_s`` (push messages after a banner), at most ``max_s``."""
        end = self._io.now_us() + max_s * 1e6
        with self._io.cond:
            while True:
                now = self._io.now_us()
                if now >= end or now - self._io.last_rx_us >= quiet_s * 1e6:
                    return
                self._io.cond.wait(quiet_s / 2)

    def _deadline_us(self, ticket: Ticket) -> float:
        base = ticket.t_sent_us + ticket.timeout_s * 1e6
        if self._io.poll_hz > 0:
            base = max(base, self._io.last_busy_us + ticket.timeout_s * 1e6)
        return base

    def _awaiting_fresh_status(self, deadline_us: float, now_us: int) -> bool:
        """Past a line's deadline, a lost 'ok' is only concluded from a status report newer than
        the deadline: a report from before it (the poller starved on a loaded host) may say Idle
        from before the cycle started. Without any report for 1 s the controller is unresponsive."""
        sample = self._io.last_sample
        return (self._io.poll_hz > 0 and sample is not None and sample.t_host_us < deadline_us
                and now_us - sample.t_host_us <= 1e6)

    def _timeout(self, ticket: Ticket, now: int) -> GrblTimeout:
        sample = self._io.last_sample
        line = ticket.line.decode()
        waited = (now - ticket.t_sent_us) / 1e6
        if self._io.poll_hz > 0 and (sample is None or now - sample.t_host_us > 1e6):
            why = "no status reports either: the controller is unresponsive (unplugged, wrong baud rate, or hung)"
        elif sample is not None:
            why = f"GRBL reports {sample.state}, so the 'ok' was lost (noise or an RX overflow)"
        else:
            why = "the 'ok' was lost or the controller is unresponsive"
        return GrblTimeout(
            f"no response to {line!r} after {waited:.1f} s ({ticket.timeout_s:.1f} s allowed); {why}; "
            "soft_reset() clears the line accounting"
        )
