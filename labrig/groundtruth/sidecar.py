"""The ground-truth sidecar file ``NAME.gt.h5`` (beside a recording, never inside it).

Datasets (N maps):

============================  ======================  ===================================================
``t_host_us``                 (N,) int64              recording host time of each map (us)
``depth_mm``                  (N, 90, 112) float32    normal displacement into the gel (mm; bulge < 0)
``contact_mask``              (N, 90, 112) uint8      1 where the indenter touches
``indentation_mm``            (N,) float32            tip below the undeformed surface (mm)
``tip_gel_mm``                (N, 3) float32          indenter tip, gel frame (mm)
``anchor_gel_mm``             (N, 2) float32          centre of the contact field (NaN out of contact)
``grid/pixel_xy``             (90, 112, 2) float64    sensor pixel (x, y) of each cell centre
``grid/gel_xy_mm``            (90, 112, 2) float64    gel-surface point (x, y) at rest seen by each cell
============================  ======================  ===================================================

Maps are zstd-compressed after a byte shuffle (hdf5plugin; a reader must ``import hdf5plugin``), one
chunk per frame. Root attributes: the models
(``elastic_model`` layer/halfspace, ``contact_model`` hertz/sneddon/numerical),
``scale_mm`` (mm per normalised unit: depth_norm = clip(depth_mm / scale_mm,
0, 1)), the gel modulus and where it, the camera and the gel pose came from,
the source recording's name and SHA-256, and more (see docs/groundtruth.md).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import hdf5plugin  # noqa: F401  (registers the maps' zstd filter for readers)
import numpy as np
import numpy.typing as npt

from labrig.groundtruth.generate import GroundTruth
from labrig.groundtruth.inputs import GroundTruthError
from labrig.recording.codecs import codec_kwargs

FORMAT = "labrig.groundtruth"


def write_sidecar(gt: GroundTruth, path: str | Path) -> Path:
    """Write ``gt`` to ``path`` atomically (a temporary file renamed over it)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    n = int(gt.t_us.size)
    # zstd after a byte shuffle: written 3x faster than gzip's level 4, 7 % more bytes, read faster.
    frames = {"chunks": (1, *gt.depth_mm.shape[1:]), "shuffle": True, **codec_kwargs("zstd")}
    try:
        with h5py.File(tmp, "w") as f:
            f.create_dataset("t_host_us", data=gt.t_us.astype(np.int64))
            if n:
                f.create_dataset("depth_mm", data=gt.depth_mm, **frames)
                f.create_dataset("contact_mask", data=gt.contact_mask, **frames)
            else:
                f.create_dataset("depth_mm", shape=(0, *gt.depth_mm.shape[1:]), dtype=np.float32)
                f.create_dataset("contact_mask", shape=(0, *gt.depth_mm.shape[1:]), dtype=np.uint8)
            f["depth_mm"].attrs["unit"] = "mm"
            f.create_dataset("indentation_mm", data=gt.indentation_mm)
            f.create_dataset("tip_gel_mm", data=gt.tip_gel_mm)
            f.create_dataset("anchor_gel_mm", data=gt.anchor_gel_mm)
            f.create_dataset("grid/pixel_xy", data=gt.grid_px)
            f.create_dataset("grid/gel_xy_mm", data=gt.grid_gel_mm)
            f["grid"].attrs["description"] = "cell (row, col) -> sensor pixel (x, y) -> gel surface (x, y) mm at rest"
            for key, value in gt.attrs.items():
                f.attrs[key] = np.asarray(value) if isinstance(value, list | tuple | np.ndarray) else value
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


@dataclass
class GroundTruthFile:
    """A loaded sidecar: arrays in memory (about 40 kB per map before compression)."""

    path: Path
    t_us: npt.NDArray[np.int64]
    depth_mm: npt.NDArray[np.float32]
    contact_mask: npt.NDArray[np.uint8]
    indentation_mm: npt.NDArray[np.float32]
    tip_gel_mm: npt.NDArray[np.float32]
    anchor_gel_mm: npt.NDArray[np.float32]
    grid_px: npt.NDArray[np.float64]
    grid_gel_mm: npt.NDArray[np.float64]
    attrs: dict[str, Any]

    @property
    def scale_mm(self) -> float:
        return float(self.attrs["scale_mm"])

    def __len__(self) -> int:
        return int(self.t_us.size)

    def nearest_index(self, t_us: float | npt.ArrayLike) -> npt.NDArray[np.int64] | int:
        """Index of the map nearest in time to ``t_us`` (scalar or array)."""
        if not len(self):
            raise GroundTruthError(f"{self.path} holds no maps")
        t = np.asarray(t_us, dtype=np.float64)
        i = np.clip(np.searchsorted(self.t_us, t), 1, len(self) - 1)
        left = self.t_us[i - 1]
        i = np.where(np.abs(t - left) <= np.abs(self.t_us[i] - t), i - 1, i)
        return int(i) if i.ndim == 0 else i.astype(np.int64)

    def nearest(self, t_us: float) -> tuple[float, npt.NDArray[np.float32], npt.NDArray[np.uint8], float]:
        """(time offset us, depth_mm map, contact mask, indentation_mm) of the map nearest to ``t_us``."""
        i = int(self.nearest_index(t_us))
        return float(self.t_us[i] - t_us), self.depth_mm[i], self.contact_mask[i], float(self.indentation_mm[i])

    def normalised(self, index: int | slice = slice(None)) -> npt.NDArray[np.float32]:
        """Depth in [0, 1] with the file's global scale."""
        return np.clip(self.depth_mm[index] / np.float32(self.scale_mm), 0.0, 1.0)

    @property
    def model(self) -> dict[str, Any]:
        return json.loads(self.attrs.get("model_json", "{}"))


def load_groundtruth(path: str | Path) -> GroundTruthFile:
    """Read a sidecar written by :func:`write_sidecar`; one-line errors for anything else."""
    path = Path(path)
    if not path.exists():
        raise GroundTruthError(f"{path}: no such ground-truth file; run `labrig groundtruth` on the recording")
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != FORMAT:
                raise GroundTruthError(f"{path} is not a labrig ground-truth sidecar (format attribute)")
            attrs = {k: (v.decode() if isinstance(v, bytes) else v.tolist() if isinstance(v, np.ndarray) else
                         v.item() if isinstance(v, np.generic) else v) for k, v in f.attrs.items()}
            return GroundTruthFile(path, f["t_host_us"][:], f["depth_mm"][:], f["contact_mask"][:],
                                   f["indentation_mm"][:], f["tip_gel_mm"][:], f["anchor_gel_mm"][:],
                                   f["grid/pixel_xy"][:], f["grid/gel_xy_mm"][:], attrs)
    except OSError as exc:
        raise GroundTruthError(f"{path} cannot be read as HDF5 ({str(exc).splitlines()[0]})") from None
    except KeyError as exc:
        raise GroundTruthError(f"{path} lacks {exc}; regenerate it with `labrig groundtruth`") from None
