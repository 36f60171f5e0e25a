"""The disk cache of contact tables: the key of every input, the cache folder, the ``.npz`` files.

A table is keyed by a SHA-256 of its full spec (indenter geometry, gel,
mode, grid, direction, footprint yaw, depth and shear sampling,
:data:`TABLE_VERSION`); stiffening is applied at lookup and is not part of the
key. The footprint yaw (and a height map's ``axis_mm``) enter the spec only
when set, so the tables of an unturned indenter keep the keys they had before
either existed. Files live under
``$LABRIG_CACHE`` (default ``~/.cache/labrig``)/contact_tables and are
written atomically (a temporary file renamed into place).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from labrig.cache import cache_folder, cache_key
from labrig.config import GelConfig
from labrig.indenters import Indenter
from labrig.physics.mechanics.grid import Grid

#: Bump when the numerics or the file layout change: old cache files are then ignored.
TABLE_VERSION = 1

#: The arrays a table file holds (attribute names of :class:`~labrig.physics.mechanics.tables.ContactTable`).
TABLE_ARRAYS = (
    "depths_mm", "depth_fields", "pressure", "normal_force_n", "shear_rows",
    "slip_shift_mm", "fractions", "traction", "shear_force_n", "window",
)


def table_spec(
    indenter: Indenter,
    gel: GelConfig,
    *,
    mode: str,
    spacing_mm: float,
    size_mm: float,
    direction_deg: float,
    yaw_deg: float = 0.0,
    depth_step_mm: float,
    max_depth_mm: float,
    shear_depth_stride: int,
    shear_steps: int,
) -> dict[str, Any]:
    """Every input that determines a table's contents (lengths mm, angles deg), as JSON-able data.

    ``yaw_deg``: the footprint's turn relative to the gel (:meth:`Indenter.footprint_yaw_deg`);
    ignored for axisymmetric indenters and left out of the spec when 0."""
    spec: dict[str, Any] = {
        "version": TABLE_VERSION,
        "indenter": _indenter_spec(indenter),
        "gel": {k: getattr(gel, k) for k in ("thickness_mm", "youngs_modulus_mpa", "poisson_ratio", "friction")},
        "mode": mode,
        "spacing_mm": float(spacing_mm),
        "grid_shape": list(Grid.centred(size_mm, spacing_mm).shape),
        "direction_deg": 0.0 if indenter.axisymmetric else float(direction_deg) % 360.0,
        "depth_step_mm": float(depth_step_mm),
        "max_depth_mm": max_depth_mm,
        "shear_depth_stride": int(shear_depth_stride),
        "shear_steps": int(shear_steps),
    }
    if not indenter.axisymmetric and float(yaw_deg) != 0.0:
        spec["yaw_deg"] = float(yaw_deg)
    return spec


def table_key(spec: dict[str, Any]) -> str:
    """The cache key of a table spec: 20 hex digits of the SHA-256 of its sorted JSON."""
    return cache_key(spec)


def table_cache_dir(cache_dir: str | Path | None = None) -> Path:
    """Where tables are cached: ``cache_dir``, else the cache root (:mod:`labrig.cache`); plus /contact_tables."""
    return cache_folder("contact_tables", cache_dir)


def table_path(indenter: Indenter, mode: str, key: str, cache_dir: str | Path | None = None) -> Path:
    """The cache file of the table with this key."""
    return table_cache_dir(cache_dir) / f"{indenter.name}-{mode}-{key}.npz"


def write_table_file(path: str | Path, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> Path:
    """Write a table's metadata and :data:`TABLE_ARRAYS` as an uncompressed ``.npz`` (atomically)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, allow_pickle=True, meta=np.array(json.dumps(meta)), **{name: arrays[name] for name in TABLE_ARRAYS})
    os.replace(tmp, path)
    return path


def read_table_file(path: str | Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(metadata, arrays) of a table file; ValueError when it was written by another :data:`TABLE_VERSION`."""
    with np.load(path) as data:
        meta = json.loads(str(data["meta"]))
        if meta.get("spec", {}).get("version") != TABLE_VERSION:
            raise ValueError(f"{path}: table version {meta.get('spec', {}).get('version')} != {TABLE_VERSION}")
        arrays = {name: data[name] for name in TABLE_ARRAYS}
    return meta, arrays


def _indenter_spec(indenter: Indenter) -> dict[str, Any]:
    spec: dict[str, Any] = {"kind": indenter.kind, "axisymmetric": indenter.axisymmetric}
    spec.update({k: v for k, v in indenter.geometry.items() if k != "file"})
    if indenter._heightmap is not None:
        spec["heightmap_sha256"] = hashlib.sha256(np.ascontiguousarray(indenter._heightmap).tobytes()).hexdigest()
    if indenter.axis_mm is not None:
        spec["axis_mm"] = list(indenter.axis_mm)
    return spec
