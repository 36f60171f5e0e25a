"""Hand tools for the rig's instruments: ``labrig cnc ...`` (GRBL) and ``labrig ft`` (Bota F/T sensor).

Mount on the main app with :func:`add_device_commands` (``cli.py``)::

    from labrig.cli_devices import add_device_commands
    add_device_commands(app)

Exit codes: 0 done; 1 the controller answered ``error:N`` to G-code you gave (``send``, ``move``,
``jog``, ``stream``; each error is printed with its meaning and line number); 2 a user error
(port cannot be opened, no answer, alarm, bad arguments), printed as one line by ``labrig``'s main.
"""

from __future__ import annotations

import json
import re
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from labrig.errors import LabrigError

console = Console()
err_console = Console(stderr=True)

JsonOption = Annotated[bool, typer.Option("--json", help="Print the result as JSON (stable keys, units in names).")]
_DEVICES_HINT = "run `labrig devices` to list the serial ports"


def _print_json(data: Any) -> None:
    sys.stdout.write(json.dumps(data, indent=2) + "\n")


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

cnc_app = typer.Typer(help="Drive the CNC (GRBL) by hand: status, unlock, home, moves, jogs, lines, programs.",
                      no_args_is_help=True)


@dataclass
class _CncTarget:
    port: str
    baud: int
    reset: str


@cnc_app.callback()
def _cnc(
    ctx: typer.Context,
    port: Annotated[str, typer.Option("--port", help="Serial port of the GRBL controller (see `labrig devices`).")],
    baud: Annotated[int, typer.Option("--baud", help="Baud rate.")] = 115200,
    reset: Annotated[str, typer.Option(
        "--reset", help="none: keep the controller as it is (homed, offsets); soft: 0x18 first; auto: DTR pulse or soft.",
    )] = "none",
) -> None:
    """Talk to a GRBL 1.1 controller on PORT."""
    if reset not in ("none", "soft", "auto"):
        raise LabrigError(f"--reset must be none, soft or auto, got {reset!r}")
    ctx.obj = _CncTarget(port, baud, reset)


@contextmanager
def _grbl(ctx: typer.Context, *, read_settings: bool = False) -> Iterator[Any]:
    from labrig.devices.grbl import Grbl, GrblConnectionError, GrblTimeout

    target: _CncTarget = ctx.obj
    grbl = Grbl(target.port, baudrate=target.baud)
    try:
        try:
            grbl.connect(reset=target.reset, read_settings=read_settings)
        except GrblConnectionError as exc:
            raise LabrigError(f"cannot use the CNC port {target.port}: {exc.__cause__ or exc}; {_DEVICES_HINT}") from None
        except GrblTimeout as exc:
            raise LabrigError(f"no answer from a GRBL controller on {target.port} at {target.baud} baud ({exc}); "
                              f"{_DEVICES_HINT}") from None
        yield grbl
    finally:
        grbl.close()


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


def _commanded(ctx: typer.Context, as_json: bool, line_hint: str | None, action: Any) -> None:
    """Run ``action(grbl) -> line sent``; then report state (exit 0) or the ``error:N`` (exit 1)."""
    from labrig.devices.grbl import GrblCommandError

    with _grbl(ctx) as grbl:
        errors = []
        try:
            action(grbl)
        except GrblCommandError as exc:
            line = exc.line.decode("ascii", "replace") if exc.line is not None else line_hint
            errors.append(_error_entry(exc.code, None, line))
        result = {**_status_dict(ctx.obj.port, grbl.status()), "errors": errors}
    if as_json:
        _print_json(result)
    else:
        for e in errors:
            _print_error(e)
        _print_status(result)
    if errors:
        raise typer.Exit(1)


@cnc_app.command("status")
def cnc_status(ctx: typer.Context, as_json: JsonOption = False) -> None:
    """State and machine position."""
    with _grbl(ctx) as grbl:
        result = _status_dict(ctx.obj.port, grbl.status())
    if as_json:
        _print_json(result)
    else:
        _print_status(result)


@cnc_app.command("unlock")
def cnc_unlock(ctx: typer.Context, as_json: JsonOption = False) -> None:
    """$X: leave Alarm without homing (the position may be wrong: home when you can)."""
    _commanded(ctx, as_json, "$X", lambda grbl: grbl.unlock())


@cnc_app.command("home")
def cnc_home(
    ctx: typer.Context,
    timeout_s: Annotated[float, typer.Option("--timeout-s", help="Allow the homing cycle this long.")] = 120.0,
    as_json: JsonOption = False,
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
    as_json: JsonOption = False,
) -> None:
    """Move (G1 at --feed, or rapid G0 without it) and wait until the machine is Idle."""
    x, y, z = _axes(target)
    if feed is not None and not feed > 0:
        raise LabrigError(f"--feed must be positive (mm/min), got {feed}")

    def action(grbl: Any) -> None:
        if relative:
            try:
                grbl.move_by(x, y, z, feed_mm_min=feed, wait=True, timeout_s=timeout_s)
            finally:
                grbl.send("G90")  # move_by leaves G91; later commands and programs expect absolute
        else:
            grbl.move_to(x, y, z, feed_mm_min=feed, wait=True, timeout_s=timeout_s)

    _commanded(ctx, as_json, None, action)


@cnc_app.command("jog", context_settings={"ignore_unknown_options": True})
def cnc_jog(
    ctx: typer.Context,
    delta: Annotated[str, typer.Argument(help="X,Y,Z in mm to jog by (empty part: axis kept, e.g. ,,-0.5).")],
    feed: Annotated[float, typer.Option("--feed", help="Feed rate, mm/min.")] = 300.0,
    as_json: JsonOption = False,
) -> None:
    """$J=: a relative jog (GRBL refuses it with error:15 if it would leave the travel); waits until Idle."""
    x, y, z = _axes(delta)
    if not feed > 0:
        raise LabrigError(f"--feed must be positive (mm/min), got {feed}")

    def action(grbl: Any) -> None:
        grbl.jog(x, y, z, feed_mm_min=feed)
        grbl.wait_idle(600.0)

    _commanded(ctx, as_json, None, action)


@cnc_app.command("send")
def cnc_send(
    ctx: typer.Context,
    line: Annotated[str, typer.Argument(help="One line: G-code or a $ command (e.g. '$$', '$G', 'G0 X5').")],
    as_json: JsonOption = False,
) -> None:
    """Send one line, wait for its answer, print what the controller said."""
    from labrig.devices.grbl import GrblCommandError

    received: list[str] = []

    def on_gcode(t_us: int, direction: int, raw: bytes) -> None:
        text = raw.decode("ascii", "replace")
        if direction == 1 and not text.startswith("<"):  # status reports are polled by the driver
            received.append(text)

    with _grbl(ctx) as grbl:
        grbl.on_gcode = on_gcode
        errors = []
        try:
            grbl.send(line)
        except GrblCommandError as exc:
            errors.append(_error_entry(exc.code, None, line))
        grbl.on_gcode = None
        result = {**_status_dict(ctx.obj.port, grbl.status()), "line": line, "response": received, "errors": errors}
    if as_json:
        _print_json(result)
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
    as_json: JsonOption = False,
) -> None:
    """Stream a program with character counting and a progress bar; report every error with its line number.

    Waits until the machine is Idle at the end. ``duration_s`` and ``lines_per_s`` cover the streaming (until the
    last line was answered). With character counting the lines already in GRBL's buffer still run after an error.
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

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

    with _grbl(ctx) as grbl, Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                      TimeElapsedColumn(), console=err_console, disable=as_json) as bar:
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
        _print_json(result)
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


# -- labrig ft ---------------------------------------------------------------------------------

_AXES = (("fx", "Fx", "n", "N"), ("fy", "Fy", "n", "N"), ("fz", "Fz", "n", "N"),
         ("tx", "Tx", "nm", "N m"), ("ty", "Ty", "nm", "N m"), ("tz", "Tz", "nm", "N m"))


def _sinc_length(rate_hz: float) -> int:
    from labrig.devices.bota_protocol import ADC_BASE_RATE_HZ, SINC_LENGTH_MAX, SINC_LENGTH_MIN

    if rate_hz > 0:
        sinc = round(ADC_BASE_RATE_HZ / rate_hz)
        if SINC_LENGTH_MIN <= sinc <= SINC_LENGTH_MAX and abs(ADC_BASE_RATE_HZ / sinc - rate_hz) <= 0.005 * rate_hz:
            return sinc
    raise LabrigError(f"--rate-hz must be {ADC_BASE_RATE_HZ} / N for N in {SINC_LENGTH_MIN}..{SINC_LENGTH_MAX} "
                      f"(e.g. 800, 400, 200, 100, 50, 25), got {rate_hz:g}")


def ft(
    port: Annotated[str, typer.Option("--port", help="Serial port of the Bota F/T sensor (see `labrig devices`).")],
    baud: Annotated[int, typer.Option("--baud", help="Baud rate.")] = 460800,
    seconds: Annotated[float, typer.Option("--seconds", help="Read this long, s.")] = 2.0,
    rate_hz: Annotated[float, typer.Option("--rate-hz", help="Sample rate to configure, Hz (51200 / sinc length).")] = 800.0,
    tare: Annotated[bool, typer.Option("--tare", help="Tare over 256 samples first (software tare).")] = False,
    as_json: JsonOption = False,
) -> None:
    """Read the force-torque sensor: rate, mean, noise and range per axis, status bits, CRC errors, frames lost."""
    import numpy as np

    from labrig.devices.bota import BotaSensor, BotaSettings
    from labrig.devices.bota_protocol import STATUS_ADVICE
    from labrig.devices.bota_stream import FtSample

    if not seconds > 0:
        raise LabrigError(f"--seconds must be positive, got {seconds:g}")
    settings = BotaSettings(sinc_length=_sinc_length(rate_hz))
    samples: list[FtSample] = []
    collecting = False

    def on_sample(sample: FtSample) -> None:
        if collecting:
            samples.append(sample)

    sensor = BotaSensor(port, baudrate=baud, on_sample=on_sample)
    try:
        with err_console.status(f"connecting to the F/T sensor on {escape(port)}") as status:
            try:
                sensor.connect()
            except LabrigError as exc:
                raise LabrigError(f"F/T sensor on {port} at {baud} baud: {exc}; {_DEVICES_HINT}") from None
            sensor.configure(settings)
            sensor.start()
            if tare:
                status.update("taring")
                sensor.tare(256)
            status.update(f"reading for {seconds:g} s")
            collecting = True
            time.sleep(seconds)
            collecting = False
        stats = sensor.stats()
    finally:
        sensor.close()

    data = np.array([(*s.force_n, *s.torque_nm) for s in samples], dtype=np.float64).reshape(-1, 6)
    t_ns = np.array([s.t_host_ns for s in samples], dtype=np.int64)
    span_s = (t_ns[-1] - t_ns[0]) / 1e9 if len(t_ns) > 1 else 0.0
    result: dict[str, Any] = {
        "port": port,
        "rate_hz": (len(samples) - 1) / span_s if span_s > 0 else 0.0,
        "nominal_rate_hz": settings.sample_rate_hz,
        "samples": len(samples),
        "duration_s": seconds,
        "tared": tare,
    }
    for i, (key, _, unit, _) in enumerate(_AXES):
        column = data[:, i]
        empty = len(column) == 0
        result[f"{key}_mean_{unit}"] = None if empty else float(column.mean())
        result[f"{key}_std_{unit}"] = None if empty else float(column.std())
        result[f"{key}_min_{unit}"] = None if empty else float(column.min())
        result[f"{key}_max_{unit}"] = None if empty else float(column.max())
    result["crc_errors"] = stats.crc_errors
    result["frames_lost"] = stats.frames_lost
    result["status_counts"] = {str(bit.name).lower(): stats.status_frames.get(str(bit.name).lower(), 0)
                               for bit in STATUS_ADVICE}
    if as_json:
        _print_json(result)
        return
    if not samples:
        raise LabrigError(f"no samples from the F/T sensor on {port} in {seconds:g} s; is it streaming? {_DEVICES_HINT}")
    console.print(f"{escape(port)}: {len(samples):,} samples at {result['rate_hz']:.1f} Hz "
                  f"(configured {settings.sample_rate_hz:g} Hz){', tared' if tare else ''}")
    table = Table(title_justify="left")
    for col in ("axis", "mean", "noise (std)", "min", "max"):
        table.add_column(col, justify="right")
    for key, name, unit, label in _AXES:
        digits = 3 if unit == "n" else 4
        values = (result[f"{key}_{what}_{unit}"] for what in ("mean", "std", "min", "max"))
        table.add_row(f"{name} ({label})", *(f"{v:.{digits}f}" for v in values))
    console.print(table)
    bad = stats.crc_errors or stats.frames_lost
    console.print(f"[{'red' if bad else 'green'}]CRC errors {stats.crc_errors}, frames lost {stats.frames_lost}[/]")
    flagged = {k: v for k, v in result["status_counts"].items() if v}
    if flagged:
        console.print("[yellow]status bits:[/] " + ", ".join(f"{k} {v}" for k, v in flagged.items()))
    else:
        console.print("status bits: none set")


def add_device_commands(app: typer.Typer) -> None:
    """Mount ``cnc`` and ``ft`` on the main app."""
    app.add_typer(cnc_app, name="cnc")
    app.command("ft")(ft)
