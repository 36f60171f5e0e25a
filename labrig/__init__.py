"""labrig: datasets and evaluation for dense 3D force estimation with an event-based tactile sensor."""

__version__ = "0.1.0"

from labrig.devices.raw import RawFile, read_raw, write_raw

__all__ = ["RawFile", "__version__", "read_raw", "write_raw"]
