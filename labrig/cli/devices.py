"""The rig's instruments: ``labrig devices`` (what is plugged in), ``labrig cnc ...`` (GRBL, in
:mod:`labrig.cli.cnc`) and ``labrig ft`` (Bota F/T sensor).

Mount on the main app with :func:`add_device_commands`. Exit codes: 0 done; 1 the controller
answered ``error:N`` (``cnc``); 2 a user error (port cannot be opened, no answer, bad arguments),
printed as one line by ``labrig``'s main.
"""

from __future__ import annotations

import time
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from labrig.cli.cnc import DEVICES_HINT, cnc_app
from labrig.cli.console import JsonOption, JsonResultOption, console, err_console, print_json
from labrig.errors import LabrigError

# -- labrig devices ----------------------------------------------------------------------------


def devices(as_json: JsonOption = False) -> None:
    """List serial ports and USB devices, and recognise the rig's instruments."""
    from labrig.devices.discovery import discover

    found = discover()
    if as_json:
        print_json(found.to_dict())
        return
    ports = Table(title="serial ports", title_justify="left")
    for col in ("port", "what", "role", "usb id", "description"):
        ports.add_column(col)
    for p in found.serial_ports:
        usb_id = f"{p.vid:04x}:{p.pid:04x}" if p.vid is not None and p.pid is not None else "-"
        ports.add_row(p.device, p.kind, p.role, usb_id, p.description)
    console.print(ports if found.serial_ports else "no serial ports found")
    for p in found.serial_ports:
        for warning in p.warnings:
            console.print(f"[yellow]warning:[/] {p.device}: {warning}")
    if found.usb_error:
        console.print(f"[yellow]USB:[/] {found.usb_error}")
    cameras = [d for d in found.usb_devices if d.role == "camera"]
    for d in cameras:
        console.print(f"camera: {d.kind} (USB {d.vid:04x}:{d.pid:04x}, bus {d.bus}, address {d.address})")
    if not found.usb_error and not cameras:
        console.print("no event camera on USB (the virtual rig is used when no hardware is configured)")
    sdk = found.metavision_sdk
    if sdk is not None and sdk.importable:
        console.print(f"Metavision SDK: metavision_hal imports ({sdk.module_path}); plugins: "
                      f"{', '.join(sdk.plugins) or 'none found'} in {', '.join(sdk.plugin_dirs) or 'no plugin folder'}; "
                      f"cameras it sees: {', '.join(sdk.cameras) or 'none'}" + (f"; [yellow]{sdk.error}[/]" if sdk.error else ""))
    elif sdk is not None:
        console.print(f"Metavision SDK: not importable ({sdk.error}); the camera = \"metavision\" backend needs it "
                      "(docs/camera.md, 'Metavision SDK')")


# -- labrig ft ---------------------------------------------------------------------------------


def ft(
    port: Annotated[str, typer.Option("--port", help="Serial port of the Bota F/T sensor (see `labrig devices`).")],
    baud: Annotated[int, typer.Option("--baud", help="Baud rate.")] = 460800,
    seconds: Annotated[float, typer.Option("--seconds", help="Read this long, s.")] = 2.0,
    rate_hz: Annotated[float, typer.Option("--rate-hz", help="Sample rate to configure, Hz (51200 / sinc length).")] = 800.0,
    tare: Annotated[bool, typer.Option("--tare", help="Tare over 256 samples first (software tare).")] = False,
    as_json: JsonResultOption = False,
) -> None:
    """Read the force-torque sensor: rate, mean, noise and range per axis, status bits, CRC errors, frames lost."""
    from labrig.devices.bota import BotaSensor, BotaSettings
    from labrig.devices.bota_protocol import STATUS_ADVICE
    from labrig.devices.bota_stream import FtSample
    from labrig.devices.ft_statistics import FT_AXES, SampleRateError, ft_statistics, sinc_length_for_rate

    if not seconds > 0:
        raise LabrigError(f"--seconds must be positive, got {seconds:g}")
    try:
        settings = BotaSettings(sinc_length=sinc_length_for_rate(rate_hz))
    except SampleRateError as exc:
        raise LabrigError(f"--rate-hz {exc}") from None
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
                raise LabrigError(f"F/T sensor on {port} at {baud} baud: {exc}; {DEVICES_HINT}") from None
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

    read = ft_statistics(samples)
    result: dict[str, Any] = {
        "port": port,
        "rate_hz": read.rate_hz,
        "nominal_rate_hz": settings.sample_rate_hz,
        "samples": read.samples,
        "duration_s": seconds,
        "tared": tare,
    }
    for key, _, unit, _ in FT_AXES:
        axis = read.axes[key]
        result.update({f"{key}_mean_{unit}": axis.mean, f"{key}_std_{unit}": axis.std,
                       f"{key}_min_{unit}": axis.min, f"{key}_max_{unit}": axis.max})
    result["crc_errors"] = stats.crc_errors
    result["frames_lost"] = stats.frames_lost
    result["status_counts"] = {str(bit.name).lower(): stats.status_frames.get(str(bit.name).lower(), 0)
                               for bit in STATUS_ADVICE}
    if as_json:
        print_json(result)
        return
    if not samples:
        raise LabrigError(f"no samples from the F/T sensor on {port} in {seconds:g} s; is it streaming? {DEVICES_HINT}")
    console.print(f"{escape(port)}: {len(samples):,} samples at {result['rate_hz']:.1f} Hz "
                  f"(configured {settings.sample_rate_hz:g} Hz){', tared' if tare else ''}")
    table = Table(title_justify="left")
    for col in ("axis", "mean", "noise (std)", "min", "max"):
        table.add_column(col, justify="right")
    for key, name, unit, label in FT_AXES:
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
    """Mount ``devices``, ``cnc`` and ``ft`` on the main app."""
    app.command("devices")(devices)
    app.add_typer(cnc_app, name="cnc")
    app.command("ft")(ft)
