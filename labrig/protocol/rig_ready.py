"""Between a campaign's runs: the rig out of Alarm before the next run, or a clear stop.

An aborted run (a force limit, a hard limit, a lost device) can leave GRBL in Alarm even after
its own recovery (the retract failed too). The next run would refuse to move, and so would every
later run of that worker. :func:`ready_for_next_run` clears it first:

* homing enabled (``$22=1``): soft reset if locked, then home (``$H``): the position is found again;
* the virtual rig: soft reset if locked, then unlock (``$X``): its twin never loses a step, so the
  position it reports is exact and the next run's travel (straight up first) is safe;
* hardware without homing: the position may be lost, so nothing moves: a :class:`SafetyError`
  says what to do, and the campaign stops (resumable) instead of failing run after run.

If clearing fails on the virtual rig, :func:`ready_or_restarted` restarts the rig instead.
"""

from __future__ import annotations

from labrig.devices.grbl import GrblAlarm, GrblError
from labrig.protocol.safety import SafetyError
from labrig.protocol.session import RigSession

#: GRBL's homing-cycle enable setting.
HOMING_ENABLE = 22


def grbl_in_alarm(session: RigSession) -> bool:
    """Whether the session's GRBL is in Alarm (a critical alarm that ignores ``?`` included)."""
    assert session.grbl is not None
    try:
        return session.grbl.status().state.startswith("Alarm")
    except GrblAlarm:
        return True


def ready_for_next_run(session: RigSession) -> str:
    """Clear an Alarm left by an earlier run; returns what was done ("" when nothing was needed)."""
    grbl = session.grbl
    assert grbl is not None
    if not grbl_in_alarm(session):
        return ""
    homing = bool(grbl.settings.get(HOMING_ENABLE, 0.0))
    if not homing and not session.virtual:
        raise SafetyError("GRBL is in Alarm after the last run and homing is off ($22=0), so its position may be "
                          "lost: check the machine, home or unlock it (labrig cnc), then rerun the campaign to resume")
    try:
        try:
            grbl.status()
        except GrblAlarm:  # a critical alarm: nothing is answered until a soft reset
            grbl.soft_reset()
        if homing:
            grbl.home()
            done = "GRBL was in Alarm after the last run: soft reset and homed ($H)"
        else:
            grbl.unlock()
            done = "GRBL was in Alarm after the last run: unlocked ($X; the virtual rig's position is exact)"
        if grbl_in_alarm(session):
            raise SafetyError("GRBL stays in Alarm after a reset and unlock: check the machine, then rerun the campaign")
    except GrblError as exc:
        raise SafetyError(f"GRBL is in Alarm after the last run and clearing it failed ({exc}): check the machine, "
                          "then rerun the campaign to resume") from exc
    return done


def ready_or_restarted(session: RigSession) -> str:
    """:func:`ready_for_next_run`; on the virtual rig a rig that cannot be cleared is restarted
    (closed and opened again: a fresh, homed twin). Returns what was done."""
    try:
        return ready_for_next_run(session)
    except SafetyError as exc:
        if not session.virtual:
            raise
        session.close()
        session.open()
        return f"{exc}; the virtual rig was restarted"
