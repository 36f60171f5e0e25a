"""Finding the rig's devices: serial ports (pyserial) and USB cameras (pyusb).

Recognises the Prophesee EVK4 / EVK3 by USB id, the usual USB-serial bridges
of CNC controllers (CH340, FTDI, CP210x, Arduino), and Bota sensors by name;
warns when an FTDI port's latency timer is at its 16 ms default (the driver
wants 1 ms for 800 Hz F/T data).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from labrig.devices.camera.metavision import MetavisionSdk, metavision_sdk

#: (vendor id, product id) -> what it is. Product id None: any product of the vendor.
USB_IDS: dict[tuple[int, int | None], str] = {
    (0x04B4, 0x00F5): "Prophesee EVK4 (IMX636)",
    (0x04B4, 0x00F4): "Prophesee EVK3",
    (0x1A86, 0x7523): "CH340 USB-serial (typical GRBL board)",
    (0x1A86, 0x5523): "CH341 USB-serial",
    (0x0403, 0x6001): "FTDI FT232R USB-serial",
    (0x0403, 0x6014): "FTDI FT232H USB-serial",
    (0x0403, 0x6015): "FTDI FT-X USB-serial",
    (0x10C4, 0xEA60): "Silicon Labs CP210x USB-serial",
    (0x2341, None): "Arduino (typical GRBL board)",
    (0x2A03, None): "Arduino (typical GRBL board)",
}
CAMERA_IDS = {(0x04B4, 0x00F5), (0x04B4, 0x00F4)}
FTDI_VENDOR = 0x0403


@dataclass(frozen=True)
class SerialPortInfo:
    device: str
    description: str
    vid: int | None
    pid: int | None
    serial_number: str | None
    kind: str
    role: str
    warnings: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class UsbDeviceInfo:
    vid: int
    pid: int
    bus: int | None
    address: int | None
    kind: str
    role: str


@dataclass(frozen=True)
class Discovery:
    serial_ports: list[SerialPortInfo]
    usb_devices: list[UsbDeviceInfo]
    usb_error: str = ""
    #: The Metavision SDK / OpenEB install, if any (the metavision camera backend needs it).
    metavision_sdk: MetavisionSdk | None = None

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


def identify(vid: int | None, pid: int | None, text: str = "") -> tuple[str, str]:
    """(what the device is, the rig role it can play) from its USB id and description."""
    if "bota" in text.lower() or "rokubi" in text.lower():
        return "Bota force-torque sensor", "ft"
    if vid is None:
        return "serial port", "unknown"
    kind = USB_IDS.get((vid, pid)) or USB_IDS.get((vid, None)) or f"USB {vid:04x}:{pid or 0:04x}"
    if (vid, pid) in CAMERA_IDS:
        return kind, "camera"
    if vid == FTDI_VENDOR:
        return kind, "cnc or ft"
    if (vid, pid) in USB_IDS or (vid, None) in USB_IDS:
        return kind, "cnc"
    return kind, "unknown"


def ftdi_latency_ms(device: str, sysfs: Path = Path("/sys/bus/usb-serial/devices")) -> int | None:
    """The FTDI latency timer of ``/dev/ttyUSBn`` in ms (Linux sysfs), if readable."""
    try:
        return int((sysfs / Path(device).name / "latency_timer").read_text().strip())
    except (OSError, ValueError):
        return None


def list_serial_ports() -> list[SerialPortInfo]:
    from serial.tools import list_ports

    ports = []
    for p in sorted(list_ports.comports(), key=lambda p: p.device):
        text = " ".join(filter(None, (p.description, p.manufacturer, p.product)))
        kind, role = identify(p.vid, p.pid, text)
        warnings = []
        if p.vid == FTDI_VENDOR:
            latency = ftdi_latency_ms(p.device)
            if latency is not None and latency > 1:
                warnings.append(
                    f"FTDI latency timer is {latency} ms: F/T frames arrive in bursts; "
                    f"set it to 1 (echo 1 | sudo tee /sys/bus/usb-serial/devices/{Path(p.device).name}/latency_timer)"
                )
        ports.append(SerialPortInfo(p.device, p.description or "", p.vid, p.pid, p.serial_number, kind, role, warnings))
    return ports


def list_usb_devices() -> tuple[list[UsbDeviceInfo], str]:
    """USB devices via pyusb; the second item says why none could be listed."""
    try:
        import usb.core
    except ImportError:
        return [], "pyusb is not installed (pip install pyusb)"
    try:
        found = list(usb.core.find(find_all=True))
    except usb.core.NoBackendError:
        return [], "libusb is missing, so USB cameras cannot be listed (Debian/Ubuntu: apt install libusb-1.0-0)"
    except usb.core.USBError as exc:
        return [], f"cannot list USB devices: {exc} (permissions? add a udev rule for the camera)"
    devices = []
    for d in found:
        kind, role = identify(d.idVendor, d.idProduct)
        devices.append(UsbDeviceInfo(d.idVendor, d.idProduct, getattr(d, "bus", None), getattr(d, "address", None), kind, role))
    return devices, ""


def discover() -> Discovery:
    usb_devices, usb_error = list_usb_devices()
    return Discovery(list_serial_ports(), usb_devices, usb_error, metavision_sdk())
