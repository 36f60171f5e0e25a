"""ROS 2 bag files through rosbags: a writer that lands atomically, a reader with one-line errors.

``OUT.mcap`` is written as one MCAP file (what ``ros2 bag play``, ``ros2 bag info`` and Foxglove
open); any other name as a bag folder (``metadata.yaml`` and the MCAP file inside). Both are written
under a temporary name beside the output and renamed when complete.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from labrig.errors import LabrigError
from labrig.recording.ros2.messages import typestore

MCAP_SUFFIX = ".mcap"
MCAP_MAGIC = b"\x89MCAP0\r\n"


class BagWriter:
    """Messages into a new ROS 2 bag (MCAP storage), one connection per topic. Use as a context manager."""

    def __init__(self, output: Path, *, overwrite: bool = False) -> None:
        self.output = Path(output)
        if self.output.exists() and not overwrite:
            raise LabrigError(f"{self.output} exists; choose another name or pass --overwrite")
        self.store = typestore()
        self._staging = self.output.with_name(self.output.name + ".partial.d")
        self._writer: Any = None
        self._connections: dict[str, Any] = {}
        self.messages = 0

    def __enter__(self) -> BagWriter:
        from rosbags.rosbag2 import StoragePlugin, Writer

        if self._staging.exists():
            shutil.rmtree(self._staging)
        self.output.parent.mkdir(parents=True, exist_ok=True)
        self._writer = Writer(self._staging, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        return self

    def topic(self, name: str, msgtype: str) -> None:
        """Declare ``name`` as a topic of ``msgtype`` (its definition goes into the bag)."""
        self._connections[name] = self._writer.add_connection(name, msgtype, typestore=self.store)

    def write(self, topic: str, log_time_ns: int, msg: Any) -> None:
        """One message; ``log_time_ns`` is the bag's receive time of it (host clock, ns)."""
        connection = self._connections[topic]
        self._writer.write(connection, int(log_time_ns), self.store.serialize_cdr(msg, connection.msgtype))
        self.messages += 1

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None:
        try:
            self._writer.close()
        finally:
            if exc is not None:
                shutil.rmtree(self._staging, ignore_errors=True)
        if exc is not None:
            return
        if self.output.is_dir():
            shutil.rmtree(self.output)
        elif self.output.exists():
            self.output.unlink()
        if self.output.suffix == MCAP_SUFFIX:
            (inner,) = self._staging.glob(f"*{MCAP_SUFFIX}")
            inner.replace(self.output)
            shutil.rmtree(self._staging)
        else:
            self._staging.replace(self.output)

    @property
    def bytes_written(self) -> int:
        if self.output.is_dir():
            return sum(p.stat().st_size for p in self.output.rglob("*") if p.is_file())
        return self.output.stat().st_size if self.output.exists() else 0


def is_bag(path: Path) -> bool:
    """Whether ``path`` is a ROS 2 bag: an MCAP file, or a folder with ``metadata.yaml``."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    if path.is_file():
        with open(path, "rb") as f:
            return f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    return False


def open_bag(path: Path) -> Any:
    """A rosbags ``Reader``, opened; a :class:`LabrigError` for a path that is not a readable bag."""
    typestore()  # the one line when rosbags is missing
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError

    if not path.exists():
        raise LabrigError(f"{path}: no such bag; give an .mcap file or a ROS 2 bag folder")
    if not is_bag(path):
        raise LabrigError(f"{path} is neither an MCAP file nor a ROS 2 bag folder (with metadata.yaml)")
    try:
        reader = Reader(path)
        reader.open()
    except (ReaderError, OSError, ValueError, KeyError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise LabrigError(f"{path}: cannot read the bag ({first})") from None
    return reader
