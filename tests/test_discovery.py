"""Device discovery: identification by USB id, FTDI latency warnings, the CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from labrig.devices.discovery import ftdi_latency_ms, identify


def test_instruments_are_recognised_by_usb_id_and_name() -> None:
    assert identify(0x04B4, 0x00F5) == ("Prophesee EVK4 (IMX636)", "camera")
    assert identify(0x04B4, 0x00F4)[1] == "camera"
    assert identify(0x1A86, 0x7523)[1] == "cnc"
    assert identify(0x2341, 0x0043)[1] == "cnc"
    assert identify(0x0403, 0x6001)[1] == "cnc or ft"
    assert identify(0x0403, 0x6015, "Bota Systems Rokubi")[1] == "ft"
    assert identify(0x1234, 0x5678) == ("USB 1234:5678", "unknown")
    assert identify(None, None) == ("serial port", "unknown")


def test_ftdi_latency_is_read_from_sysfs(tmp_path: Path) -> None:
    (tmp_path / "ttyUSB0").mkdir()
    (tmp_path / "ttyUSB0" / "latency_timer").write_text("16\n")
    assert ftdi_latency_ms("/dev/ttyUSB0", tmp_path) == 16
    assert ftdi_latency_ms("/dev/ttyUSB1", tmp_path) is None


def test_devices_command_works_without_hardware() -> None:
    result = subprocess.run([sys.executable, "-m", "labrig.cli", "devices", "--json"], capture_output=True, text=True,
                            timeout=60, check=False)
    assert result.returncode == 0, result.stderr
    found = json.loads(result.stdout)
    assert set(found) == {"serial_ports", "usb_devices", "usb_error", "metavision_sdk"}
    text = subprocess.run([sys.executable, "-m", "labrig.cli", "devices"], capture_output=True, text=True, timeout=60,
                          check=False)
    assert text.returncode == 0 and ("USB" in text.stdout or "camera" in text.stdout)
