"""Result files of ``labrig run``: per-window markers, displacements and force fields in HDF5.

Forces are on the gel (pressing: Fz < 0), gel frame, N; positions in sensor pixels; times in
the stream's time base, us (a recording's host time, or a live camera's device time). ``rest_mm``
(M, 3), where given, holds the markers' rest points on the gel surface (gel frame, mm), so that a
reader places the force field without the rig; the attribute ``t0_host_ns`` (a recording's) puts the
times on its host clock.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from labrig.errors import LabrigError
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.runtime import WindowResult

RESULT_FORMAT = "labrig.forces"
RESULT_VERSION = 1


class ResultWriter:
    """Per-window force fields into an HDF5 file (datasets grow one row per window).

    Rows are buffered and written ``FLUSH_ROWS`` at a time (one HDF5 chunk; a row at a time
    costs about 6 ms, more than the pipeline's own work per window); :meth:`close` writes the rest.
    """

    FLUSH_ROWS = 64

    FIELDS: tuple[tuple[str, str, tuple[int | str, ...], str], ...] = (  # shape: "M" is the marker count
        ("t0_us", "<i8", (), "us"), ("t1_us", "<i8", (), "us"), ("n_events", "<i8", (), ""),
        ("positions_px", "<f4", ("M", 2), "px"), ("updated", "u1", ("M",), ""),
        ("displacement_mm", "<f4", ("M", 3), "mm"), ("forces_n", "<f4", ("M", 3), "N"),
        ("net_force_n", "<f8", (3,), "N"), ("contact_px", "<f8", (2,), "px"), ("contact_mm", "<f8", (2,), "mm"),
        ("processing_s", "<f8", (), "s"),
    )

    def __init__(self, path: str | Path, n_markers: int, attrs: dict[str, Any], depth: bool = False,
                 rest_mm: Any = None) -> None:
        """``depth``: keep each window's depth map (``depth_mm``, (W, 90, 112) mm); ``rest_mm``: the markers'
        rest points (M, 3), gel frame, mm."""
        import h5py

        self.path = Path(path)
        self.file = h5py.File(self.path, "w")
        self.file.attrs["format"] = RESULT_FORMAT
        self.file.attrs["format_version"] = RESULT_VERSION
        for key, value in attrs.items():
            self.file.attrs[key] = value
        self.n = 0
        self._pending: list[dict[str, Any]] = []
        for name, dtype, shape, unit in self.FIELDS:
            dims = tuple(n_markers if d == "M" else d for d in shape)
            ds = self.file.create_dataset(name, shape=(0, *dims), maxshape=(None, *dims), dtype=dtype,
                                          chunks=(64, *dims), compression="gzip" if dims else None)
            ds.attrs["unit"] = unit
        if rest_mm is not None:
            ds = self.file.create_dataset("rest_mm", data=np.asarray(rest_mm, np.float64).reshape(n_markers, 3))
            ds.attrs["unit"] = "mm"
        if depth:
            ds = self.file.create_dataset("depth_mm", shape=(0, *GRID_SHAPE), maxshape=(None, *GRID_SHAPE),
                                          dtype="<f4", chunks=(8, *GRID_SHAPE), compression="gzip")
            ds.attrs["unit"] = "mm"

    def write(self, r: WindowResult) -> None:
        values = {"t0_us": r.t0_us, "t1_us": r.t1_us, "n_events": r.n_events, "positions_px": r.positions_px,
                  "updated": r.updated, "displacement_mm": r.displacement_mm, "forces_n": r.forces_n,
                  "net_force_n": r.net_force_n, "contact_px": r.contact_px, "contact_mm": r.contact_mm,
                  "processing_s": sum(r.seconds.values())}
        if "depth_mm" in self.file:
            values["depth_mm"] = r.depth_mm
        self._pending.append(values)
        if len(self._pending) >= self.FLUSH_ROWS:
            self.flush()

    def flush(self) -> None:
        """Write the buffered rows."""
        if not self._pending:
            return
        rows, self._pending = self._pending, []
        for name in rows[0]:  # the per-window datasets (rest_mm is written once)
            ds = self.file[name]
            ds.resize(self.n + len(rows), axis=0)
            ds[self.n:] = np.stack([np.asarray(row[name]) for row in rows])
        self.n += len(rows)

    def close(self) -> None:
        self.flush()
        self.file.attrs["windows"] = self.n
        self.file.close()

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def is_result_file(path: str | Path) -> bool:
    """Whether ``path`` is a result file of ``labrig run --out`` (an HDF5 file with ``format = labrig.forces``)."""
    import h5py

    p = Path(path)
    if not p.is_file() or not h5py.is_hdf5(p):
        return False
    with h5py.File(p, "r") as f:
        return bool(f.attrs.get("format") == RESULT_FORMAT)


def load_result(path: str | Path) -> dict[str, Any]:
    """A result file as {dataset: array} plus ``attrs``."""
    import h5py

    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != RESULT_FORMAT:
            raise LabrigError(f"{path}: not a labrig force result file")
        out: dict[str, Any] = {name: f[name][()] for name in f}
        out["attrs"] = {k: (v.item() if hasattr(v, "item") else v) for k, v in f.attrs.items()}
    return out
