"""Ground-truth normal-deformation maps for one recording, from what a lab knows.

Pipeline (docs/groundtruth.md):

1. **Tool pose** at the output times (:class:`ToolTrack`): the recording's CNC
   status stream (10 Hz) interpolated linearly, with knots added at the ends of
   every Wait phase (the machine stands still over a wait, at the position its
   polls there report), so the interpolation does not cut the corners where
   moves start and stop. Moves run at constant feed between their short
   accelerations, which linear interpolation follows.
2. **Indentation** (:func:`kinematics`): tool + the indenter's tool offset is
   the tip, mapped into the gel frame with the rig registration (or the
   nominal pose). The contact point is the tip where the approach phase ended;
   the indentation is the tip's travel below it along the gel normal, plus the
   depth at which the approach detected contact (the force model inverted at
   the F/T reading there: 0 when the approach ended at the surface).
   The field is centred at the contact point; in shear it stays there while
   the tip moves within the gross-slip shift of the contact (stick and partial
   slip) and is dragged along beyond it; lift-off resets it.
3. **Maps** on the network grid: the ROI of the sensor resized to 90 x 112
   cells; each cell's sensor pixel is back-projected through the camera
   calibration to the gel surface; the contact model (:mod:`contact`) gives uz
   and the contact mask there, a non-axisymmetric indenter's field turned by its yaw
   relative to the gel (:mod:`turned`).
4. **Normalisation**: one global scale ``scale_mm`` (mm per unit), depth_norm
   = clip(depth_mm / scale_mm, 0, 1); stored with the maps, depth_mm kept.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig import __version__
from labrig.cache import sha256_of
from labrig.groundtruth.contact import ContactModel, choose_model
from labrig.groundtruth.inputs import GroundTruthError, LabInputs, lab_inputs, recording_rig
from labrig.groundtruth.turned import turned_model
from labrig.indenters import DEFAULT_INDENTERS, Indenter, IndenterError, indenter_from_toml, load_indenters
from labrig.physics.grid import GRID_SHAPE, network_grid_gel_mm, network_grid_pixels
from labrig.recording import Phase, Recording

F64 = npt.NDArray[np.float64]

#: Default global normalisation scale, mm per unit (the deepest indentation any default indenter allows).
DEFAULT_SCALE_MM = 2.5
#: F/T samples averaged at the end of the approach (the runner's contact detection uses 16).
CONTACT_SAMPLES = 16
#: Below this force at the end of the approach, the approach ended at the surface.
CONTACT_FORCE_FLOOR_N = 0.02


# ------------------------------------------------------------------------------------ tool pose


class ToolTrack:
    """Tool reference point (machine mm) over host time from the CNC status stream."""

    def __init__(self, t_us: npt.ArrayLike, position_mm: npt.ArrayLike, phases: list[Phase] = ()) -> None:  # type: ignore[assignment]
        t = np.asarray(t_us, dtype=np.float64)
        p = np.asarray(position_mm, dtype=np.float64).reshape(-1, 3)
        if t.size == 0:
            raise GroundTruthError("the recording has no CNC status samples: the tool pose is unknown")
        knots_t, knots_p = [t], [p]
        for ph in phases:
            if not ph.name.startswith("wait"):
                continue
            inside = (t > ph.t_start_us) & (t < ph.t_end_us)
            if inside.any():
                still = np.median(p[inside], axis=0)
                knots_t.append(np.array([ph.t_start_us, ph.t_end_us], dtype=np.float64))
                knots_p.append(np.stack([still, still]))
        t_all, p_all = np.concatenate(knots_t), np.concatenate(knots_p)
        order = np.argsort(t_all, kind="stable")
        t_all, p_all = t_all[order], p_all[order]
        keep = np.concatenate([[True], np.diff(t_all) > 0])
        self.t_us, self.position_mm = t_all[keep], p_all[keep]

    def __call__(self, t_us: npt.ArrayLike) -> F64:
        t = np.atleast_1d(np.asarray(t_us, dtype=np.float64))
        return np.stack([np.interp(t, self.t_us, self.position_mm[:, i]) for i in range(3)], axis=-1)


@dataclass
class Kinematics:
    t_us: npt.NDArray[np.int64]
    tip_gel_mm: F64  # (N, 3)
    indentation_mm: F64  # (N,)
    anchor_mm: F64  # (N, 2), nan out of contact
    contact_tip_gel_mm: F64  # (3,)
    contact_offset_mm: float
    contact_force_n: float
    surface_method: str


def _phase_end(phases: list[Phase], name: str) -> int | None:
    for ph in phases:
        if ph.name == name:
            return ph.t_end_us
    return None


def approach_force_n(ft: dict[str, np.ndarray], t_end_us: int) -> float:
    """Mean |F| of the last F/T samples of the approach (the tared force at the contact point)."""
    if not len(ft.get("t_us", ())):
        return 0.0
    t = ft["t_us"]
    idx = np.flatnonzero(t <= t_end_us)[-CONTACT_SAMPLES:]
    if idx.size == 0:
        return 0.0
    return float(np.linalg.norm(ft["force_n"][idx].astype(np.float64).mean(axis=0)))


def depth_at_force(force_of_depth: Callable[[float], float], force_n: float, max_depth_mm: float) -> float:
    """The depth where the force model reaches ``force_n`` (bisection; 0 below the floor)."""
    if force_n <= CONTACT_FORCE_FLOOR_N:
        return 0.0
    lo, hi = 0.0, max_depth_mm
    if force_of_depth(hi) < force_n:
        return hi
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if force_of_depth(mid) < force_n:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


#: The depth tables of a press that reaches past its indenter's ``max_depth_mm`` go this much deeper at a time (mm),
#: so that the presses of a campaign share a few tables.
TABLE_REACH_STEP_MM = 0.25


def _force_curve(model: ContactModel, lab: LabInputs) -> Callable[[float], float]:
    """The normal force (N) at a depth (mm), with the gel's stiffening."""
    h = lab.gel.thickness_mm
    return lambda d: model.force_n(d) * (1.0 + lab.stiffening * d / h)


def deepest_indentation_mm(t_us: npt.ArrayLike, track: ToolTrack, phases: list[Phase], indenter: Indenter,
                           lab: LabInputs, force_model: ContactModel, contact_force_n: float) -> float:
    """The deepest indentation (mm) :func:`kinematics` gives at ``t_us``, without the contact model's fields: the
    depth at contact plus the tip's deepest travel below the contact point (below the surface without an approach
    phase). A press whose contact came at a depth (a pin's or a texture's small area under the approach's
    contact force) reaches past the travel the protocol asked for."""
    machine_to_gel = lab.gel_pose.inverse()
    offset = np.asarray(indenter.tool_offset_mm, dtype=np.float64)
    tip_z = machine_to_gel.apply(track(np.asarray(t_us, dtype=np.int64)) + offset)[:, 2]
    t_contact = _phase_end(phases, "approach")
    if t_contact is None:
        return float(max(-tip_z.min(initial=0.0), 0.0))
    contact_z = machine_to_gel.apply(track([t_contact])[0] + offset)[2]
    d0 = depth_at_force(_force_curve(force_model, lab), contact_force_n, indenter.max_depth_mm)
    return float(d0 + max(contact_z - tip_z.min(initial=contact_z), 0.0))


def kinematics(t_us: npt.ArrayLike, track: ToolTrack, phases: list[Phase], indenter: Indenter, lab: LabInputs,
               model: ContactModel, contact_force_n: float, force_model: ContactModel | None = None) -> Kinematics:
    """Indentation and contact centre at ``t_us`` (see the module docstring)."""
    t = np.asarray(t_us, dtype=np.int64)
    machine_to_gel = lab.gel_pose.inverse()
    offset = np.asarray(indenter.tool_offset_mm, dtype=np.float64)
    tip = machine_to_gel.apply(track(t) + offset)
    t_contact = _phase_end(phases, "approach")
    force_curve = _force_curve(force_model or model, lab)
    if t_contact is not None:
        contact_tip = machine_to_gel.apply(track([t_contact])[0] + offset)
        d0 = depth_at_force(force_curve, contact_force_n, indenter.max_depth_mm)
        depth = d0 + (contact_tip[2] - tip[:, 2])
        method = "approach end + F/T"
    else:  # no approach phase: the registered (or nominal) surface, z = 0 of the gel frame
        contact_tip, d0 = np.array([np.nan, np.nan, 0.0]), 0.0
        depth = -tip[:, 2]
        method = "gel pose surface (no approach phase)"
    anchor = np.full((t.size, 2), np.nan)
    current: F64 | None = None
    for i in range(t.size):
        if depth[i] <= 0:
            current = None
            continue
        if current is None:
            current = tip[i, :2].copy()
        shift = tip[i, :2] - current
        size = float(np.hypot(*shift))
        limit = model.slip_shift_mm(float(depth[i]), shift if size > 0 else None)
        if limit > 0 and size > limit:  # gross slip drags the contact along
            current = tip[i, :2] - shift * (limit / size)
        anchor[i] = current
    return Kinematics(t, tip, np.maximum(depth, 0.0), anchor, contact_tip, float(d0), float(contact_force_n), method)


# ------------------------------------------------------------------------------------ maps


@dataclass
class GroundTruth:
    """Maps and everything needed to interpret them (see :func:`write_sidecar` for the file)."""

    t_us: npt.NDArray[np.int64]
    depth_mm: npt.NDArray[np.float32]  # (N, 90, 112)
    contact_mask: npt.NDArray[np.uint8]
    indentation_mm: npt.NDArray[np.float32]
    tip_gel_mm: npt.NDArray[np.float32]
    anchor_gel_mm: npt.NDArray[np.float32]
    grid_px: npt.NDArray[np.float64]  # (90, 112, 2) sensor pixel (x, y) of each cell centre
    grid_gel_mm: npt.NDArray[np.float64]  # (90, 112, 2) gel-surface point at rest of each cell
    scale_mm: float
    attrs: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def depth_norm(self) -> npt.NDArray[np.float32]:
        return np.clip(self.depth_mm / np.float32(self.scale_mm), 0.0, 1.0)


def recording_indenter(path: Path, name: str, definition: str, indenters_path: str | Path = DEFAULT_INDENTERS) -> Indenter:
    """The indenter a recording was made with: its own stored definition, else (recordings made
    before they carried one) ``name`` in the indenters file."""
    if definition:
        try:
            return indenter_from_toml(definition, str(path))
        except IndenterError as exc:
            raise GroundTruthError(str(exc)) from None
    indenters = load_indenters(indenters_path)
    if name not in indenters:
        raise GroundTruthError(f"{path}: indenter {name!r} is not in {indenters_path} and the recording carries no "
                               "definition of it; give the lab's indenters file with --indenters")
    return indenters[name]


def generate(
    recording: str | Path,
    *,
    elastic: str = "layer",
    method: str = "auto",
    rate_hz: float = 100.0,
    scale_mm: float = DEFAULT_SCALE_MM,
    calibration_dir: str | Path | None = None,
    rig_path: str | Path | None = None,
    indenters_path: str | Path = DEFAULT_INDENTERS,
    lab: LabInputs | None = None,
    table_options: dict[str, Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> GroundTruth:
    """Ground truth for one recording (never reads its ``/truth`` streams)."""
    start = time.perf_counter()
    path = Path(recording)
    if rate_hz <= 0 or scale_mm <= 0:
        raise GroundTruthError("the rate and the scale must be positive")
    with Recording(path) as rec:
        attrs = rec.attrs
        name = str(attrs.get("indenter", ""))
        if not name:
            raise GroundTruthError(f"{path} does not name its indenter (root attribute 'indenter')")
        indenter = recording_indenter(path, name, str(attrs.get("indenter_definition", "")), indenters_path)
        if lab is None:
            rig, rig_source = recording_rig(str(attrs.get("rig", "")), rig_path, str(path))
            lab = lab_inputs(rig, calibration_dir)
            lab.sources["rig"] = rig_source
        phases = rec.phases()
        cnc_t = rec.column("cnc", "t_host_us")
        track = ToolTrack(cnc_t, rec.column("cnc", "position_mm"), phases)
        ft = rec.ft() if rec.rows("ft") else {}
    times = _output_times(ft.get("t_us"), cnc_t, rate_hz)
    options = dict(table_options or {})
    t_contact = _phase_end(phases, "approach")
    contact_force = approach_force_n(ft, t_contact) if t_contact is not None else 0.0
    force_model = choose_model(indenter, lab.gel, "layer", "numerical", **options)
    reach = deepest_indentation_mm(times, track, phases, indenter, lab, force_model, contact_force)
    if reach > options.get("max_depth_mm", indenter.max_depth_mm):  # the tables reach as deep as this press went
        options["max_depth_mm"] = TABLE_REACH_STEP_MM * float(np.ceil(reach / TABLE_REACH_STEP_MM + 1e-9))
        force_model = choose_model(indenter, lab.gel, "layer", "numerical", **options)
    model = turned_model(choose_model(indenter, lab.gel, elastic, method, **options), indenter, lab.gel_pose)
    kin = kinematics(times, track, phases, indenter, lab, model, contact_force, force_model)
    grid_px = network_grid_pixels(lab.rig, GRID_SHAPE)
    grid_gel = network_grid_gel_mm(lab.rig, lab.camera, GRID_SHAPE)
    n = times.size
    depth = np.zeros((n, *GRID_SHAPE), np.float32)
    mask = np.zeros((n, *GRID_SHAPE), np.uint8)
    gx, gy = grid_gel[..., 0], grid_gel[..., 1]
    for i in range(n):
        if kin.indentation_mm[i] > 0 and np.isfinite(kin.anchor_mm[i, 0]):
            uz, contact = model.fields(float(kin.indentation_mm[i]), gx - kin.anchor_mm[i, 0], gy - kin.anchor_mm[i, 1])
            depth[i], mask[i] = np.round(uz, 4), contact  # 0.1 um: far below any error, compresses 2-3x
        if progress is not None and (i % 50 == 49 or i == n - 1):
            progress(i + 1, n)
    meta = {
        "format": "labrig.groundtruth",
        "format_version": "1.0",
        "labrig_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "source_recording": path.name,
        "source_sha256": sha256_of(path),
        "indenter": name,
        "indenter_kind": indenter.kind,
        "elastic_model": model.elastic,
        "contact_model": model.method,
        "model_json": _json(model.describe()),
        "youngs_modulus_mpa": lab.gel.youngs_modulus_mpa,
        "poisson_ratio": lab.gel.poisson_ratio,
        "thickness_mm": lab.gel.thickness_mm,
        "stiffening": lab.stiffening,
        "gel_source": lab.sources["gel"],
        "camera_source": lab.sources["camera"],
        "gel_pose_source": lab.sources["gel_pose"],
        "rig_source": lab.sources.get("rig", "given"),
        "recording_calibration_json": str(attrs.get("extra_calibration", "")),
        "camera_json": _json({k: getattr(lab.camera, k) for k in (
            "fx_px", "fy_px", "cx_px", "cy_px", "distortion", "gel_to_camera_rotvec_rad",
            "gel_to_camera_translation_mm", "width_px", "height_px")}),
        "gel_in_machine_rotation": lab.gel_pose.rotation,
        "gel_in_machine_translation_mm": lab.gel_pose.translation_mm,
        "roi_px": [lab.rig.roi.x0_px, lab.rig.roi.y0_px, lab.rig.roi.x1_px, lab.rig.roi.y1_px],
        "rate_hz": float(rate_hz),
        "time_source": "F/T sample times" if len(ft.get("t_us", ())) else "CNC time span",
        "pose_method": "CNC status stream, linear, + Wait-phase knots",
        "surface_method": kin.surface_method,
        "contact_tip_gel_mm": kin.contact_tip_gel_mm,
        "contact_offset_mm": kin.contact_offset_mm,
        "contact_force_n": kin.contact_force_n,
        "scale_mm": float(scale_mm),
        "normalisation": "depth_norm = clip(depth_mm / scale_mm, 0, 1)",
    }
    return GroundTruth(times, depth, mask, kin.indentation_mm.astype(np.float32), kin.tip_gel_mm.astype(np.float32),
                       kin.anchor_mm.astype(np.float32), grid_px, grid_gel, float(scale_mm), meta,
                       time.perf_counter() - start)


def _output_times(ft_t_us: np.ndarray | None, cnc_t_us: np.ndarray, rate_hz: float) -> npt.NDArray[np.int64]:
    """F/T sample times thinned to about ``rate_hz`` (or a uniform grid over the CNC span without F/T)."""
    if ft_t_us is not None and len(ft_t_us) > 1:
        t = np.asarray(ft_t_us, dtype=np.int64)
        period = float(np.median(np.diff(t)))
        step = max(1, round(1e6 / rate_hz / max(period, 1.0)))
        return t[::step]
    lo, hi = float(cnc_t_us[0]), float(cnc_t_us[-1])
    return np.arange(lo, hi + 1, 1e6 / rate_hz).astype(np.int64)


def _json(value: Any) -> str:
    import json

    return json.dumps(value, default=lambda v: v.tolist() if hasattr(v, "tolist") else str(v))
