"""The virtual rig's devices served to other processes (``labrig sim serve``).

GRBL and Bota answer on pseudo-terminals, the EVK4 streams EVT3 on a Unix socket (see
:class:`~labrig.sim.world.LiveWorld`); real drivers, any other GRBL sender or Bota client open
the terminals as serial ports, the camera's ``sim`` backend reads the socket. Optional stable
names: symlinks ``DIR/grbl``, ``DIR/bota``, ``DIR/evk4`` to the devices, removed on exit.
"""

from __future__ import annotations

import tempfile
import threading
from pathlib import Path
from types import TracebackType

from labrig.config import RigConfig
from labrig.errors import LabrigError
from labrig.indenters import Indenter
from labrig.sim.world import LiveWorld

#: How often the serving loop looks at the world's health and the stop request, s.
POLL_S = 0.2


class DeviceServer:
    """The virtual rig's devices, served while the context is open; :meth:`serve` waits in between.

    Building it loads the indenter's contact tables (seconds on a cold cache). Without
    ``camera_socket`` the EVK4's socket is ``evk4.sock`` in a fresh temporary directory.
    """

    def __init__(self, rig: RigConfig, indenter: Indenter, *, seed: int = 0, homed: bool = True,
                 camera_socket: Path | None = None, links: Path | None = None) -> None:
        self._socket_dir: tempfile.TemporaryDirectory[str] | None = None
        if camera_socket is None:
            self._socket_dir = tempfile.TemporaryDirectory(prefix="labrig-")
            camera_socket = Path(self._socket_dir.name) / "evk4.sock"
        self.links = links
        self._made: list[Path] = []
        self.world = LiveWorld(rig, indenter, seed=seed, camera_socket=camera_socket, homed=homed)

    @property
    def paths(self) -> dict[str, str]:
        """Device paths by name: ``grbl``, ``bota`` (pseudo-terminals), ``evk4`` (the socket)."""
        return self.world.paths

    def __enter__(self) -> DeviceServer:
        self.world.start()
        try:
            if self.links is not None:
                for name, path in self.world.paths.items():
                    self._made.append(_link(self.links, name, path))
        except BaseException:
            self._close()
            raise
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self._close()

    def _close(self) -> None:
        try:
            for link in self._made:
                link.unlink(missing_ok=True)
            self.world.stop()
        finally:
            if self._socket_dir is not None:
                self._socket_dir.cleanup()

    def serve(self, *, stop: threading.Event, seconds: float | None = None) -> None:
        """Serve until ``stop`` is set, ``seconds`` of world time have passed or Ctrl-C; raise if the rig fails."""
        world = self.world
        try:
            while not stop.wait(POLL_S):
                if world.error is not None or world.server.error is not None:
                    raise LabrigError(f"the virtual rig stopped: {world.error or world.server.error!r}")
                if seconds is not None and world.now_world_us() >= seconds * 1e6:
                    break
        except KeyboardInterrupt:
            pass

    @property
    def served_s(self) -> float:
        """World time since the devices started, s."""
        return self.world.now_world_us() / 1e6

    @property
    def stats(self) -> dict[str, float | int]:
        """The renderer's statistics (stable keys, units in names)."""
        return self.world.stats.as_dict()


def _link(directory: Path, name: str, target: str) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    link = directory / name
    if link.is_symlink() or link.exists():
        if not link.is_symlink():
            raise LabrigError(f"{link} exists and is not a symlink; choose another --links directory")
        link.unlink()
    link.symlink_to(target)
    return link
