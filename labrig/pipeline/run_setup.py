"""What is fixed for a run: the rig, the camera, the markers' rest pixels, the gel law and the camera's contrast
thresholds, and where each came from.

The gel modulus is the fitted one (``calibration/gel.toml``) when present, else the rig's;
the camera is the calibrated one (``calibration/intrinsics.toml`` + ``extrinsics.toml``)
when present, else the rig file's nominal one (lens and sensor). The markers' rest pixels are those the extrinsic calibration
measured (its marker map: where each marker really is, the nominal lattice only where one is
missing), with the missing markers flagged; without a calibration, the nominal lattice through
that camera. The contrast thresholds are the measured ones (``calibration/events.toml``) when
present, else none (every event counts one: the nominal sensor). :func:`setup_for_recording`
resolves both for a recording, :func:`setup_for_rig` for a live stream.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from labrig.calibration.event_thresholds_file import EVENTS_FILE, ContrastThresholds, load_event_thresholds
from labrig.calibration.files import camera_from_calibration, load_extrinsics, load_intrinsics, uncalibrated_camera
from labrig.calibration.gel import load_gel
from labrig.config import DEFAULT_CALIBRATION_DIR, RigConfig, load_rig
from labrig.dataset import events_sidecar_path
from labrig.physics.camera import CameraModel
from labrig.recording import Recording

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class PipelineSetup:
    """Everything fixed for a run: rig, camera, rest pixels, gel modulus and where they came from."""

    rig: RigConfig
    camera: CameraModel
    rest_px: Array
    youngs_modulus_mpa: float
    poisson_ratio: float
    sources: dict[str, str]
    stiffening: float = 0.0  # E_eff = E (1 + stiffening * depth / thickness); 0: linear (the paper's)
    missing: npt.NDArray[np.bool_] | None = None  # (M,) markers the calibration found missing; None: none
    thresholds: ContrastThresholds | None = None  # the camera's contrast thresholds per grid cell; None: nominal

    @property
    def observed(self) -> npt.NDArray[np.bool_]:
        """(M,) markers that are tracked (not missing)."""
        return np.ones(len(self.rest_px), bool) if self.missing is None else ~np.asarray(self.missing, bool)

    def rest_mm(self, rest_px: npt.ArrayLike | None = None) -> Array:
        """(M, 3) the markers' rest points on the gel surface (z = 0), gel frame mm: ``rest_px`` (default:
        :attr:`rest_px`) back-projected, so a marker printed off its lattice site rests where it is."""
        return rest_points_mm(self.camera, self.rest_px if rest_px is None else rest_px)


def rest_points_mm(camera: CameraModel, rest_px: npt.ArrayLike) -> Array:
    """(M, 3) gel-frame points (z = 0) that the pixels ``rest_px`` (M, 2) see."""
    return camera.backproject_to_plane(np.asarray(rest_px, np.float64), 0.0)


def rig_from_recording(recording: Recording) -> RigConfig | None:
    """The rig TOML the recording carries (root attribute ``rig``), or None."""
    text = recording.attrs.get("rig", "")
    if not isinstance(text, str) or not text.strip():
        return None
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "rig.toml"
        path.write_text(text)
        return load_rig(path)


def _named_calibration(recording: Recording) -> dict[str, Path]:
    """Calibration files the recording names (``extra_calibration``: JSON {path: sha256}) that still exist."""
    raw = recording.attrs.get("extra_calibration", "")
    try:
        named = json.loads(raw) if isinstance(raw, str) and raw else {}
    except json.JSONDecodeError:
        named = {}
    return {Path(p).name: Path(p) for p in named if Path(p).exists()}


def setup_for_recording(recording: Recording, *, rig: RigConfig | None = None,
                        calibration_dir: str | Path | None = DEFAULT_CALIBRATION_DIR,
                        youngs_modulus_mpa: float | None = None, poisson_ratio: float | None = None,
                        stiffening: float | None = None) -> PipelineSetup:
    """Rig, camera, rest pixels and gel modulus for ``recording``.

    Rig: ``rig``, else the one the recording carries, else calibration/rig.toml. Files: those
    the recording names, else ``calibration_dir`` (None: none); the contrast thresholds of its own
    camera (``NAME.events.toml`` beside it, :func:`labrig.dataset.events_sidecar_path`) before
    either; then as :func:`setup_for_rig`.
    """
    stored = None if rig is not None else rig_from_recording(recording)
    rig = rig or stored or load_rig()
    named = _named_calibration(recording)
    own_events = events_sidecar_path(recording.path)
    if own_events.exists():
        named[EVENTS_FILE] = own_events
    setup = setup_for_rig(rig, calibration_dir=calibration_dir, youngs_modulus_mpa=youngs_modulus_mpa,
                          poisson_ratio=poisson_ratio, stiffening=stiffening, named=named)
    if stored is not None:  # read from a temporary copy: name where it lives
        setup = replace(setup, sources={**setup.sources, "rig": f"{recording.path} (the rig file it carries)"})
    return setup


def setup_for_rig(rig: RigConfig, *, calibration_dir: str | Path | None = DEFAULT_CALIBRATION_DIR,
                  youngs_modulus_mpa: float | None = None, poisson_ratio: float | None = None,
                  stiffening: float | None = None, named: dict[str, Path] | None = None) -> PipelineSetup:
    """Camera, rest pixels and gel law for ``rig`` (a live stream, or a recording's rig).

    Files: ``named`` ({file name: path}) first, else ``calibration_dir`` (None: none). Modulus
    and stiffening: the arguments, else gel.toml, else the rig's [gel] modulus and a linear gel
    (stiffening 0). Camera: intrinsics.toml + extrinsics.toml, else the rig's. Contrast thresholds:
    events.toml, else nominal.
    """
    sources: dict[str, str] = {"rig": str(rig.path)}
    files = dict(named or {})
    if calibration_dir is not None:
        for name in ("gel.toml", "intrinsics.toml", "extrinsics.toml", EVENTS_FILE):
            candidate = Path(calibration_dir) / name
            if name not in files and candidate.exists():
                files[name] = candidate
    e, nu, b = rig.gel.youngs_modulus_mpa, rig.gel.poisson_ratio, 0.0
    sources["modulus"], sources["stiffening"] = "rig [gel]", "linear gel"
    if "gel.toml" in files and (youngs_modulus_mpa is None or stiffening is None):
        fitted = load_gel(files["gel.toml"])
        if youngs_modulus_mpa is None:
            e = float(fitted.get("youngs_modulus_mpa", e))
            nu = float(fitted.get("poisson_ratio", nu))
            sources["modulus"] = str(files["gel.toml"])
        if stiffening is None and "stiffening" in fitted:
            b, sources["stiffening"] = float(fitted["stiffening"]), str(files["gel.toml"])
    if youngs_modulus_mpa is not None:
        e, sources["modulus"] = float(youngs_modulus_mpa), "argument"
    if poisson_ratio is not None:
        nu = float(poisson_ratio)
    if stiffening is not None:
        b, sources["stiffening"] = float(stiffening), "argument"
    rest_px, missing = None, None
    if "intrinsics.toml" in files and "extrinsics.toml" in files:
        extrinsics = load_extrinsics(files["extrinsics.toml"])
        camera = camera_from_calibration(load_intrinsics(files["intrinsics.toml"]), extrinsics)
        sources["camera"] = f"{files['intrinsics.toml']} + {files['extrinsics.toml']}"
        sources["rest"] = "nominal lattice through the camera (no extrinsics.toml)"
        marker_map = extrinsics.marker_map
        if len(marker_map.rest_px) == rig.markers.rows * rig.markers.cols:
            rest_px, missing = marker_map.rest_px, marker_map.missing
            sources["rest"] = (f"measured ({files['extrinsics.toml']}, format {extrinsics.format_version}; "
                               f"{int(missing.sum())} missing)")
    else:
        camera, sources["camera"] = uncalibrated_camera(rig)
        sources["rest"] = "nominal lattice through the camera (no extrinsics.toml)"
    if rest_px is None:
        rest_px = camera.project(rig.markers.rest_positions_mm())
    thresholds, sources["thresholds"] = None, "nominal (no events.toml: every event counts one)"
    if EVENTS_FILE in files:
        thresholds = load_event_thresholds(files[EVENTS_FILE])
        thresholds.check_roi(rig.roi)
        sources["thresholds"] = str(files[EVENTS_FILE])
        sources["slope_gain"] = (f"{thresholds.slope_gain:.3g} ({files[EVENTS_FILE]})" if thresholds.slope_gain is not None
                                 else f"not measured ({files[EVENTS_FILE]} has no [shading])")
    return PipelineSetup(rig, camera, rest_px, e, nu, sources, stiffening=b, missing=missing, thresholds=thresholds)
