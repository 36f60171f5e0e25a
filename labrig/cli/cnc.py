"""``labrig cnc ...``: drive the CNC (GRBL) by hand.

Mounted on the main app by :func:`labrig.cli.devices.add_device_commands`.

``move``, ``jog``, ``send`` and ``stream`` check every straight move they would command against the
motion envelope of the rig file and the mounted indenter (:mod:`labrig.protocol.envelope`), from
where the controller stands (its machine position, ``$G`` and ``$#``), and refuse before sending
anything: a move outside it, or one whose path cannot be known beforehand (arcs, probing,
``G28``/``G30``, anything after homing or a reset in a program). ``--outside-envelope`` sends it
anyway, with a warning. ``status``, ``unlock`` and ``home`` are not checked.

Exit codes: 0 done; 1 the controller answered ``error:N`` to G-code you gave (``send``, ``move``,
``jog``, ``stream``; each error is printed with its meaning and line number); 2 a user error
(port cannot be opened, no answer, alarm, bad arguments, a refused move), printed as one line by
``labrig``'s main.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.progress import MofNCompleteColumn, TimeElapsedColumn

from labrig.cli.console import (
    IndentersOption,
    JsonResultOption,
    RigOption,
    console,
    err_console,
    print_json,
    progress_bar,
)
from labrig.errors import LabrigError

DEVICES_HINT = "run `labrig devices` to list the serial ports"
OVERRIDE_HINT = "pass --outside-envelope to send it anyway"
OutsideEnvelopeOption = Annotated[bool, typer.Option(
    "--outside-envelope", help="Send it even where it leaves the motion envelope (maintenance: nothing is checked; "
    "prints a warning).")]


def _axes(text: str) -> tuple[float | None, float | None, float | None]:
    """``X,Y,Z`` with empty parts left out (``,,-2``: only Z)."""
    parts = text.split(",")
    if len(parts) != 3:
        raise LabrigError(f"give the target as X,Y,Z in mm (leave a part empty to keep that axis, e.g. ,,-2), got {text!r}")
    values: list[float | None] = []
    for part in parts:
        try:
            values.append(float(part) if part.strip() else None)
        except ValueError:
            raise LabrigError(f"{part!r} in {text!r} is not a number; give X,Y,Z in mm") from None
    if all(v is None for v in values):
        raise LabrigError(f"{text!r} gives no axis; give X,Y,Z in mm (e.g. 10,0,-2 or ,,-2)")
    return values[0], values[1], values[2]


# -- labrig cnc --------------------------------------------------------------------------------

cnc_app = typer.Typer(help="Drive the CNC (GRBL) by hand: status, unlock, home, moves, jogs, lines, programs.\n\n"
                      "move, jog, send and stream refuse, before sending anything, motion that leaves the rig's "
                      "envelope: outside the \\[safety] workspace, deeper into the gel than the indenter's max_depth_mm, "
                      "below the gel surface beside it (the sensor body), or a straight path through them; and motion "
                      "they cannot follow (arcs, probing, G28/G30). --outside-envelope sends it anyway (docs/running.md).",
                      no_args_is_help=True)


@dataclass
class _CncTarget:
    port: str
    baud: int
    reset: str
    rig: Path | None
    indenters: Path | None
    indenter: str | None


@cnc_app.callback()
def _cnc(
    ctx: typer.Context,
    port: Annotated[str, typer.Option("--port", help="Serial port of the GRBL controller (see `labrig devices`).")],
    baud: Annotated[int, typer.Option("--baud", help="Baud rate.")] = 115200,
    reset: Annotated[str, typer.Option(
        "--reset", help="none: keep the controller as it is (homed, offsets); soft: 0x18 first; auto: DTR pulse or soft.",
    )] = "none",
    rig: RigOption = None,
    indenters: IndentersOption = None,
    indenter: Annotated[str | None, typer.Option(
        "--indenter", help="The mounted indenter (a name in --indenters), for the motion envelope of move, jog, send "
        "and stream (default: the one whose tip reaches lowest, the most conservative).")] = None,
) -> None:
    """Talk to a GRBL 1.1 controller on PORT."""
    if reset not in ("none", "soft", "auto"):
        raise LabrigError(f"--reset must be none, soft or auto, got {reset!r}")
    ctx.obj = _CncTarget(port, baud, reset, rig, indenters, indenter)


@contextmanager
def _grbl(ctx: typer.Context, *, read_settings: bool = False) -> Iterator[Any]:
    from labrig.devices.grbl import Grbl, GrblConnectionError, GrblTimeout

    target: _CncTarget = ctx.obj
    grbl = Grbl(target.port, baudrate=target.baud)
    try:
        try:
            grbl.connect(reset=target.reset, read_settings=read_settings)
        except GrblConnectionError as exc:
            raise LabrigError(f"cannot use the CNC port {target.port}: {exc.__cause__ or exc}; {DEVICES_HINT}") from None
        except GrblTimeout as exc:
            raise LabrigError(f"no answer from a GRBL controller on {target.port} at {target.baud} baud ({exc}); "
                              f"{DEVICES_HINT}") from None
        yield grbl
    finally:
        grbl.close()


def _envelope(target: _CncTarget) -> tuple[Any, str]:
    """The motion envelope of the rig file and the mounted indenter, and what it was built from (text)."""
    from labrig.cli.console import load_rig_and_indenters
    from labrig.protocol.envelope import MotionEnvelope, most_conservative_indenter

    rig, indenters, path = load_rig_and_indenters(target.rig, target.indenters)
    if target.indenter is None:
        indenter = most_conservative_indenter(indenters)
        chosen = (f"indenter {indenter.name}, the default: the one in {path.name} whose tip reaches lowest; name the "
                  "mounted one with --indenter")
    elif target.indenter in indenters:
        indenter = indenters[target.indenter]
        chosen = f"indenter {indenter.name}"
    else:
        raise LabrigError(f"--indenter {target.indenter!r} is not in {path}; give one of {', '.join(indenters)}")
    return MotionEnvelope.of(rig, indenter), f"envelope of {rig.path} with {chosen}"


def _check_motion(grbl: Any, target: _CncTarget, lines: list[str], labels: list[str], outside_envelope: bool) -> None:
    """Refuse (:class:`~labrig.protocol.envelope.EnvelopeError`, before anything is sent) lines whose
    motion leaves the envelope or cannot be known beforehand; ``labels`` name them in the refusal.

    The controller is asked for its position, ``$G`` and ``$#`` only when a line could move.
    """
    from labrig.devices.grbl_program import ProgramTracker, may_move
    from labrig.protocol.envelope import EnvelopeError

    if outside_envelope:
        err_console.print("[yellow]warning:[/] --outside-envelope: this motion is not checked against the rig's "
                          "workspace, gel and sensor body", highlight=False, soft_wrap=True)
        return
    if not any(may_move(line) for line in lines):
        return
    envelope, built_from = _envelope(target)
    state = grbl.status().state
    if state not in ("Idle", "Alarm"):
        raise EnvelopeError(f"the CNC is {state}: the motion envelope check starts from the parser's position and "
                            "offsets, which GRBL gives only while Idle or in Alarm; wait until it is Idle (leave check "
                            f"mode with `send '$C'`), or {OVERRIDE_HINT}")
    tracker = ProgramTracker(*grbl.gcode_state(), alarm=state == "Alarm")
    for line, label in zip(lines, labels, strict=True):
        motion = tracker.line(line)
        if motion.unchecked is not None:
            raise EnvelopeError(f"refused before sending anything: {label}: {motion.unchecked}, so its motion cannot be "
                                f"checked against the {built_from}; {OVERRIDE_HINT}")
        for start, end in motion.segments:
            problem = envelope.segment_problem(start, end)
            if problem is not None:
                raise EnvelopeError(f"refused before sending anything: {label}: {problem} ({built_from}); {OVERRIDE_HINT}")


def _status_dict(port: str, sample: Any) -> dict[str, Any]:
    return {
        "port": port,
        "state": sample.state,
        "position_mm": list(sample.position_mm),
        "feed_mm_min": sample.feed_mm_min,
    }


def _print_status(d: dict[str, Any]) -> None:
    style = {"Idle": "green", "Alarm": "red"}.get(d["state"].split(":")[0], "yellow")
    x, y, z = d["position_mm"]
    console.print(f"{escape(d['port'])}: [{style}]{escape(d['state'])}[/]  machine position "
                  f"X {x:.3f}  Y {y:.3f}  Z {z:.3f} mm")


def _error_entry(code: int, line_number: int | None, line: str | None) -> dict[str, Any]:
    from labrig.devices.grbl_protocol import error_meaning

    return {"line_number": line_number, "line": line, "code": code, "meaning": error_meaning(code)}


def _print_error(e: dict[str, Any]) -> None:
    where = f"line {e['line_number']}: " if e["line_number"] is not None else ""
    line = f" in {e['line']!r}" if e["line"] is not None else ""
    err_console.print(f"[red]{where}error:{e['code']}[/] {escape(e['meaning'])}{escape(line)}", highlight=False)


def _commanded(ctx: typer.Context, as_json: bool, line_hint: str | None, action: Any, check: Any = None) -> None:
    """Run ``check(grbl)`` (refusing raises), then ``action(grbl)``; then report state (exit 0) or the ``error:N`` (exit 1)."""
    from labrig.devices.grbl import GrblCommandError

    with _grbl(ctx) as grbl:
        if check is not None:
            check(grbl)
        errors = []
        try:
            action(grbl)
        except GrblCommandError as exc:
            line = exc.line.decode("ascii", "replace") if exc.line is not None else line_hint
            errors.append(_error_entry(exc.code, None, line))
        result = {**_status_dict(ctx.obj.port, grbl.status()), "errors": errors}
    if as_json:
        print_json(result)
    else:
        for e in errors:
            _print_error(e)
        _print_status(result)
    if errors:
        raise typer.Exit(1)


@cnc_app.command("status")
def cnc_status(ctx: typer.Context, as_json: JsonResultOption = False) -> None:
    """State and machine position."""
    with _grbl(ctx) as grbl:
        result = _status_dict(ctx.obj.port, grbl.status())
    if as_json:
        print_json(result)
    else:
        _print_status(result)


@cnc_app.command("unlock")
def cnc_unlock(ctx: typer.Context, as_json: JsonResultOption = False) -> None:
    """$X: leave Alarm without homing (the position may be wrong: home when you can)."""
    _commanded(ctx, as_json, "$X", lambda grbl: grbl.unlock())


@cnc_app.command("home")
def cnc_home(
    ctx: typer.Context,
    timeout_s: Annotated[float, typer.Option("--timeout-s", help="Allow the homing cycle this long.")] = 120.0,
    as_json: JsonResultOption = False,
) -> None:
    """$H: run the homing cycle (needs homing enabled, $22=1)."""
    _commanded(ctx, as_json, "$H", lambda grbl: grbl.home(timeout_s=timeout_s))


FeedOption = Annotated[float | None, typer.Option("--feed", help="Feed rate, mm/min.")]


@cnc_app.command("move", context_settings={"ignore_unknown_options": True})
def cnc_move(
    ctx: typer.Context,
    target: Annotated[str, typer.Argument(help="X,Y,Z in mm (work coordinates; empty part: axis kept, e.g. ,,-2).")],
    feed: FeedOption = None,
    relative: Annotated[bool, typer.Option("--relative", help="Move by X,Y,Z instead of to it.")] = False,
    timeout_s: Annotated[float, typer.Option("--timeout-s", help="Allow the move this long.")] = 600.0,
    outside_envelope: OutsideEnvelopeOption = False,
    as_json: JsonResultOption = False,
) -> None:
    """Move (G1 at --feed, or rapid G0 without it) and wait until the machine is Idle.

    Refused before sending if the straight move leaves the motion envelope (see `labrig cnc --help`).
    """
    from labrig.devices.grbl_protocol import motion_line

    x, y, z = _axes(target)
    if feed is not None and not feed > 0:
        raise LabrigError(f"--feed must be positive (mm/min), got {feed}")
    line = ("G91" if relative else "G90") + motion_line(x, y, z, feed)  # what the driver sends
    label = f"move {'by' if relative else 'to'} {target} ({line})"

    def action(grbl: Any) -> None:
        if relative:
            try:
                grbl.move_by(x, y, z, feed_mm_min=feed, wait=True, timeout_s=timeout_s)
            finally:
                grbl.send("G90")  # move_by leaves G91; later commands and programs expect absolute
        else:
            grbl.move_to(x, y, z, feed_mm_min=feed, wait=True, timeout_s=timeout_s)

    _commanded(ctx, as_json, None, action, lambda grbl: _check_motion(grbl, ctx.obj, [line], [label], outside_envelope))


@cnc_app.command("jog", context_settings={"ignore_unknown_options": True})
def cnc_jog(
    ctx: typer.Context,
    delta: Annotated[str, typer.Argument(help="X,Y,Z in mm to jog by (empty part: axis kept, e.g. ,,-0.5).")],
    feed: Annotated[float, typer.Option("--feed", help="Feed rate, mm/min.")] = 300.0,
    outside_envelope: OutsideEnvelopeOption = False,
    as_json: JsonResultOption = False,
) -> None:
    """$J=: a relative jog (GRBL refuses it with error:15 if it would leave the travel); waits until Idle.

    Refused before sending if the jog leaves the motion envelope (see `labrig cnc --help`).
    """
    from labrig.devices.grbl_protocol import jog_line

    x, y, z = _axes(delta)
    if not feed > 0:
        raise LabrigError(f"--feed must be positive (mm/min), got {feed}")
    line = jog_line(x, y, z, feed_mm_min=feed)  # what the driver sends

    def action(grbl: Any) -> None:
        grbl.jog(x, y, z, feed_mm_min=feed)
        grbl.wait_idle(600.0)

    _commanded(ctx, as_json, None, action,
               lambda grbl: _check_motion(grbl, ctx.obj, [line], [f"jog by {delta} ({line})"], outside_envelope))


@cnc_app.command("send")
def cnc_send(
    ctx: typer.Context,
    line: Annotated[str, typer.Argument(help="One line: G-code or a $ command (e.g. '$$', '$G', 'G0 X5').")],
    outside_envelope: OutsideEnvelopeOption = False,
    as_json: JsonResultOption = False,
) -> None:
    """Send one line, wait for its answer, print what the controller said.

    A line that moves is refused before sending if it leaves the motion envelope or its path cannot be
    known beforehand (arcs, probing, G28/G30; see `labrig cnc --help`).
    """
    from labrig.devices.grbl import GrblCommandError

    received: list[str] = []

    def on_gcode(t_us: int, direction: int, raw: bytes) -> None:
        text = raw.decode("ascii", "replace")
        if direction == 1 and not text.startswith("<"):  # status reports are polled by the driver
            received.append(text)

    with _grbl(ctx) as grbl:
        _check_motion(grbl, ctx.obj, [line], [repr(line)], outside_envelope)
        grbl.on_gcode = on_gcode
        errors = []
        try:
            grbl.send(line)
        except GrblCommandError as exc:
            errors.append(_error_entry(exc.code, None, line))
        grbl.on_gcode = None
        result = {**_status_dict(ctx.obj.port, grbl.status()), "line": line, "response": received, "errors": errors}
    if as_json:
        print_json(result)
    else:
        for text in received:
            if not (errors and text.startswith("error:")):  # printed below with its meaning
                console.print(escape(text), highlight=False)
        for e in errors:
            _print_error(e)
    if errors:
        raise typer.Exit(1)


_RESPONSE = re.compile(r"^(ok|error:(\d+))$")


def _program(file: Path) -> tuple[list[str], list[int]]:
    """The lines to send and their line numbers in the file (blank lines, ``;`` comments and ``%`` skipped)."""
    try:
        text = file.read_text(encoding="ascii", errors="replace")
    except OSError as exc:
        raise LabrigError(f"cannot read the G-code file {file}: {exc.strerror or exc}") from None
    lines, numbers = [], []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith((";", "%")):
            continue
        lines.append(line)
        numbers.append(number)
    return lines, numbers


@cnc_app.command("stream")
def cnc_stream(
    ctx: typer.Context,
    file: Annotated[Path, typer.Argument(help="G-code program (one block per line).")],
    send_response: Annotated[bool, typer.Option(
        "--send-response", help="One line at a time instead of character counting (slower, simplest).")] = False,
    keep_going: Annotated[bool, typer.Option(
        "--keep-going", help="Send the rest of the program after an error (default: stop at the first).")] = False,
    outside_envelope: OutsideEnvelopeOption = False,
    as_json: JsonResultOption = False,
) -> None:
    """Stream a program with character counting and a progress bar; report every error with its line number.

    Waits until the machine is Idle at the end. ``duration_s`` and ``lines_per_s`` cover the streaming (until the
    last line was answered). With character counting the lines already in GRBL's buffer still run after an error.
    The whole program is checked against the motion envelope first, following the position from line to line
    (see `labrig cnc --help`); a refused line stops it before any line is sent.
    """
    from labrig.devices.grbl import GrblCommandError

    program, numbers = _program(file)
    if not program:
        raise LabrigError(f"{file} has no G-code lines")
    mode = "send-response" if send_response else "count"
    # Every line sent is answered in order by ok or error:N, so the k-th answer belongs to the k-th line.
    answers: list[int | None] = []

    def on_gcode(t_us: int, direction: int, raw: bytes) -> None:
        if direction == 1:
            match = _RESPONSE.match(raw.decode("ascii", "replace").strip())
            if match:
                answers.append(int(match.group(2)) if match.group(2) else None)

    labels = [f"{file.name} line {n} {text!r}" for n, text in zip(numbers, program, strict=True)]
    with _grbl(ctx) as grbl:
        _check_motion(grbl, ctx.obj, program, labels, outside_envelope)
        with progress_bar(MofNCompleteColumn(), TimeElapsedColumn(), disable=as_json) as bar:
            task = bar.add_task(f"streaming {file.name}", total=len(program))
            grbl.on_gcode = on_gcode
            start = 0
            t0 = time.perf_counter()
            while start < len(program):
                try:
                    grbl.stream(program[start:], mode=mode,
                                progress=lambda done, _total, offset=start: bar.update(task, completed=offset + done))
                    start = len(program)
                except GrblCommandError:
                    start = len(answers)  # every line sent so far was answered before stream() raised
                    if not keep_going:
                        break
            duration_s = time.perf_counter() - t0
            grbl.on_gcode = None
            bar.update(task, description=f"{file.name}: waiting for the motion to finish")
            final = grbl.wait_idle(timeout_s=3600.0)
    errors = [_error_entry(code, numbers[i], program[i]) for i, code in enumerate(answers) if code is not None]
    result = {
        **_status_dict(ctx.obj.port, final),
        "file": str(file),
        "mode": mode,
        "lines_total": len(program),
        "lines_sent": len(answers),
        "errors": errors,
        "stopped_early": len(answers) < len(program),
        "duration_s": duration_s,
        "lines_per_s": len(answers) / max(duration_s, 1e-9),
    }
    if as_json:
        print_json(result)
    else:
        for e in errors:
            _print_error(e)
        style = "red" if errors else "green"
        stopped = f" (stopped after the first error; {len(program) - len(answers)} not sent)" if result["stopped_early"] else ""
        console.print(f"[{style}]{len(answers)}/{len(program)} lines sent, {len(errors)} error(s){stopped}[/] "
                      f"in {duration_s:.2f} s ({result['lines_per_s']:.1f} lines/s)")
        _print_status(result)
    if errors:
        raise typer.Exit(1)
