"""Gel-to-camera extrinsics from events of the LED ring blinking, gel at rest.

1. The ON events of the blinks' ON switches and the OFF events of their OFF
   switches are counted per pixel and combined by their harmonic mean
   (:func:`.eventframes.harmonic_frame`: the per-pixel threshold mismatch,
   which at high noise makes membrane specks as bright as markers, is tamed).
2. Markers are found by a disc matched filter at the size that responds most
   strongly (:func:`.eventframes.find_discs`), each peak with a strength in
   noise sigmas; up to twice as many candidates as markers are kept.
3. Association with the known rows x cols grid, robust to missing and
   spurious candidates and to the grid's orientation in the image: the centres
   are undistorted with the intrinsics (so the grid is a homography image of
   the plane); pitch and lattice directions come from the nearest-neighbour
   vectors of the rows x cols strongest candidates (angle folded four times,
   so both axes agree; the pitch is the median of every link near it, not of
   the nearest neighbour alone, which placement errors bias short); integer lattice coordinates are rounded in that basis
   from the most central of them, then a RANSAC homography from lattice to
   image re-assigns them three times. Candidates further than 0.35 pitch
   from their lattice site are spurious, a site keeps its strongest candidate,
   and the rows x cols window (either way round) with the largest total
   strength is the grid.
4. Sub-pixel centres: disc-model fits (:func:`.eventframes.fit_discs`), first
   free on the strongest, then with their common radius and edge width fixed.
5. A planar grid is symmetric: its 180-degree turn and its mirror images
   (equivalent to viewing the plane from the other side) fit equally well.
   Of the four labellings, the one whose PnP rotation is closest to the
   nominal gel-to-camera rotation is kept (``nominal_rotvec_rad``, the rig
   file's ``[camera] nominal_rotvec_rad``; the reference sensor's camera sits
   below the gel looking up, image x along gel x, image y along gel y).
6. Markers without a candidate are fitted where that pose projects them, or at
   the nearest blob no marker took if one lies within 0.45 pitch (a marker
   printed that far off its site);
   ``cv2.solvePnPRefineLM`` refines the pose, markers off by more than
   max(3 x median, 1 px) are left out of it and it is refined again; the
   per-marker reprojection errors are reported.
7. The markers as printed (:class:`~labrig.calibration.marker_map.MarkerMap`):
   every measured centre is kept, those left out of the pose included (a
   marker printed off its site is still where it is); a marker with neither a
   candidate nor a guided fit is missing. Residuals: measured less the nominal
   lattice projected through the pose (px), and on the gel plane (mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from labrig.cache import sha256_of
from labrig.calibration.eventframes import (
    Blobs,
    accumulate_polarities,
    find_blinks,
    find_discs,
    fit_discs,
    harmonic_frame,
)
from labrig.calibration.files import (
    DEFAULT_EXTRINSICS,
    EXTRINSICS_FORMAT_VERSION,
    Intrinsics,
    marker_map_table,
    provenance,
    save_text_atomic,
    toml_table,
)
from labrig.calibration.intrinsics import sensor_size
from labrig.calibration.marker_map import MarkerMap
from labrig.config import MarkerConfig
from labrig.errors import CalibrationError
from labrig.frames import rotvec_to_matrix
from labrig.physics.camera import CameraModel
from labrig.recording import Recording

Array = npt.NDArray[np.float64]

NOMINAL_ROTVEC_RAD = (0.0, 0.0, 0.0)
#: A candidate further than this (in pitches) from its nearest lattice site is not associated: a third of
#: the pitch keeps the rounding unambiguous and takes markers printed up to about 0.15 pitch (std) off their sites.
ASSOCIATION_TOLERANCE = 0.35
#: An unassociated blob this near an empty lattice site (in pitches) is where the guided fit of that site starts.
FREE_CANDIDATE_PITCHES = 0.45


@dataclass
class ExtrinsicsResult:
    rotvec_rad: Array
    translation_mm: Array
    rest_gel_mm: Array  # (rows*cols, 3), node order row-major from -y, -x
    rest_px: Array  # projections of rest_gel_mm through the fitted pose, (rows*cols, 2)
    measured_px: Array  # detected centres, NaN where a marker was not detected (missing)
    errors_px: Array  # per marker |measured - projected|, NaN where not detected
    blobs: Blobs
    spurious: int
    blinks: int
    frame: Array
    markers: MarkerConfig
    in_pose: npt.NDArray[np.bool_]  # (M,) measured markers the pose was fitted on
    marker_map: MarkerMap  # the markers as printed: measured rest, missing, residuals
    recording: Path | None = None
    recording_sha256: str = ""

    @property
    def detected(self) -> npt.NDArray[np.bool_]:
        return np.isfinite(self.errors_px)

    @property
    def mean_error_px(self) -> float:
        """Mean reprojection error over the markers the pose was fitted on (px)."""
        return float(np.mean(self.errors_px[self.in_pose]))

    @property
    def std_error_px(self) -> float:
        return float(np.std(self.errors_px[self.in_pose]))

    @property
    def max_error_px(self) -> float:
        return float(np.max(self.errors_px[self.in_pose]))


def associate_grid(
    points_px: Array, intrinsics: Intrinsics, rows: int, cols: int, strength: npt.ArrayLike | None = None
) -> tuple[npt.NDArray[np.int64], int]:
    """For each point, its (row, col) in the grid up to the grid's symmetry, or (-1, -1); and the spurious count.

    The returned labelling has ``cols`` along one lattice axis and ``rows``
    along the other; which way round and which signs are settled by PnP
    against the nominal rotation (:func:`choose_orientation`). With
    ``strength`` (one per point, larger is more marker-like) the lattice
    (pitch, axes, seed) comes from the ``rows x cols`` strongest points only,
    a lattice site claimed by several points keeps the strongest, and the
    window with the largest total strength is the grid; without it every point
    counts the same and a site keeps the point nearest to it.
    """
    n = len(points_px)
    labels = np.full((n, 2), -1, np.int64)
    if n < 8:
        return labels, 0
    weight = np.ones(n) if strength is None else np.asarray(strength, np.float64)
    und = cv2.undistortPoints(points_px.reshape(-1, 1, 2).astype(np.float64), intrinsics.matrix,
                              np.asarray(intrinsics.distortion), P=intrinsics.matrix).reshape(-1, 2)
    from scipy.spatial import cKDTree

    core = np.zeros(n, bool)
    core[np.argsort(-weight, kind="stable")[: rows * cols] if strength is not None else slice(None)] = True
    pts = und[core]
    if len(pts) < 8:
        return labels, 0
    dist, idx = cKDTree(pts).query(pts, k=5)
    vectors = (pts[idx[:, 1:]] - pts[:, None, :]).reshape(-1, 2)
    lengths = dist[:, 1:].ravel()
    pitch = float(np.median(dist[:, 1]))
    ok = (lengths > 0.7 * pitch) & (lengths < 1.4 * pitch)
    # The nearest of four noisy neighbours is biased short (14 % at a placement error of a tenth of the
    # pitch), which misrounds the lattice a few pitches out; every link in the band is not.
    pitch = float(np.median(lengths[ok]))
    ok = (lengths > 0.7 * pitch) & (lengths < 1.4 * pitch)
    angles = np.arctan2(vectors[ok, 1], vectors[ok, 0])
    theta = float(np.angle(np.mean(np.exp(4j * angles)))) / 4
    basis = np.array([[np.cos(theta), np.sin(theta)], [-np.sin(theta), np.cos(theta)]]) * pitch  # rows: a, b
    seed = pts[np.argmin(np.linalg.norm(pts - np.median(pts, axis=0), axis=1))]
    lattice = np.rint(np.linalg.solve(basis.T, (und - seed).T).T)
    inlier = core.copy()
    for _ in range(3):
        h, _ = cv2.findHomography(lattice[inlier], und[inlier], cv2.RANSAC, 0.3 * pitch)
        if h is None:
            return labels, 0
        back = cv2.perspectiveTransform(und.reshape(-1, 1, 2), np.linalg.inv(h)).reshape(-1, 2)
        lattice = np.rint(back)
        inlier = np.linalg.norm(back - lattice, axis=1) < ASSOCIATION_TOLERANCE
    # One point per lattice site: the strongest, or the nearest.
    residual = np.linalg.norm(back - lattice, axis=1)
    order = np.argsort(residual) if strength is None else np.argsort(-weight, kind="stable")
    seen: set[tuple[int, int]] = set()
    for k in order:
        key = (int(lattice[k, 0]), int(lattice[k, 1]))
        if not inlier[k] or key in seen:
            inlier[k] = False
            continue
        seen.add(key)
    if inlier.sum() < 4:
        return labels, int(n)
    lat = lattice.astype(np.int64)
    best = (-1.0, 0, 0, 0)  # total weight, swap, i0, j0
    for swap, (na, nb) in enumerate(((cols, rows), (rows, cols))):
        ia, ib, w = lat[inlier, 0], lat[inlier, 1], weight[inlier]
        for i0 in range(ia.min(), ia.max() - na + 2):
            for j0 in range(ib.min(), ib.max() - nb + 2):
                total = float(w[(ia >= i0) & (ia < i0 + na) & (ib >= j0) & (ib < j0 + nb)].sum())
                if total > best[0]:
                    best = (total, swap, i0, j0)
    _, swap, i0, j0 = best
    na, nb = ((cols, rows), (rows, cols))[swap]
    inside = inlier & (lat[:, 0] >= i0) & (lat[:, 0] < i0 + na) & (lat[:, 1] >= j0) & (lat[:, 1] < j0 + nb)
    a, b = lat[:, 0] - i0, lat[:, 1] - j0
    col, row = (a, b) if swap == 0 else (b, a)
    labels[inside, 0] = row[inside]
    labels[inside, 1] = col[inside]
    return labels, int(n - inside.sum())


def choose_orientation(
    points_px: Array,
    labels: npt.NDArray[np.int64],
    markers: MarkerConfig,
    intrinsics: Intrinsics,
    nominal_rotvec_rad: tuple[float, float, float] = NOMINAL_ROTVEC_RAD,
) -> tuple[npt.NDArray[np.int64], Array, Array]:
    """Of the grid's four symmetric labellings, the one whose PnP pose is nearest the nominal rotation.

    Returns (marker index per point or -1, rvec, tvec)."""
    rows, cols = markers.rows, markers.cols
    rest = markers.rest_positions_mm()
    good = labels[:, 0] >= 0
    nominal = rotvec_to_matrix(nominal_rotvec_rad)
    best: tuple[float, npt.NDArray[np.int64], Array, Array] | None = None
    for flip_r in (False, True):
        for flip_c in (False, True):
            r = np.where(flip_r, rows - 1 - labels[:, 0], labels[:, 0])
            c = np.where(flip_c, cols - 1 - labels[:, 1], labels[:, 1])
            index = np.where(good, r * cols + c, -1)
            ok, rvec, tvec = cv2.solvePnP(rest[index[good]], points_px[good], intrinsics.matrix,
                                          np.asarray(intrinsics.distortion), flags=cv2.SOLVEPNP_ITERATIVE)
            if not ok:
                continue
            rot = rotvec_to_matrix(rvec.ravel())
            angle = float(np.arccos(np.clip((np.trace(nominal.T @ rot) - 1) / 2, -1, 1)))
            if best is None or angle < best[0]:
                best = (angle, index, cast(Array, rvec.ravel()), cast(Array, tvec.ravel()))
    if best is None:
        raise CalibrationError("PnP failed for every orientation of the marker grid")
    return best[1], best[2], best[3]


def _pose(obj: Array, img: Array, intrinsics: Intrinsics, rvec: Array, tvec: Array) -> tuple[Array, Array]:
    """solvePnPRefineLM from (rvec, tvec)."""
    refined = cv2.solvePnPRefineLM(obj, img, intrinsics.matrix, np.asarray(intrinsics.distortion),
                                   rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy(),
                                   criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    rvec, tvec = cast(tuple[Array, Array], refined)
    return rvec.ravel(), tvec.ravel()


def measure_markers(
    frame: Array, candidates: Blobs, labels: npt.NDArray[np.int64], markers: MarkerConfig, intrinsics: Intrinsics,
    nominal_rotvec_rad: tuple[float, float, float] = NOMINAL_ROTVEC_RAD,
) -> tuple[Array, npt.NDArray[np.bool_], Array, Array]:
    """Sub-pixel marker centres (rows*cols, 2; NaN where not measured), which of them the pose was fitted
    on, and the pose (rvec, tvec).

    The matched candidates' discs are fitted freely (the strongest 40 give the
    markers' common radius and edge width), then all with that size fixed; the
    orientation is chosen (:func:`choose_orientation`); markers without a
    candidate are fitted where the pose projects them (kept if the fit stays
    within 2 px and its contrast is at least half the typical); after an LM
    refinement, markers off by more than max(3 x median, 1 px) are left out of
    the pose (their centres are kept: a marker printed off its site is still
    measured) and the pose refined again."""
    n_markers = markers.rows * markers.cols
    rest = markers.rest_positions_mm()
    good = np.flatnonzero(labels[:, 0] >= 0)
    start = candidates.xy[good]
    radius = float(np.median(candidates.radius_px)) if len(candidates) else 5.0
    strongest = np.argsort(-(candidates.strength[good] if candidates.strength is not None else np.ones(len(good))))
    free = fit_discs(frame, start[strongest[:40]], radius)
    if free.ok.sum() >= 3:
        radius, edge = float(np.median(free.radius_px[free.ok])), float(np.median(free.edge_px[free.ok]))
    else:
        edge = 0.8
    fixed = fit_discs(frame, start, radius, fixed_radius=radius, edge_px=edge)
    fitted = np.full_like(candidates.xy, np.nan)
    fitted[good[fixed.ok]] = fixed.xy[fixed.ok]
    labels = np.where(np.isfinite(fitted[:, :1]), labels, -1)
    index, rvec, tvec = choose_orientation(np.nan_to_num(fitted), labels, markers, intrinsics, nominal_rotvec_rad)
    measured = np.full((n_markers, 2), np.nan)
    measured[index[index >= 0]] = fitted[index >= 0]
    dist = np.asarray(intrinsics.distortion)
    missing = np.flatnonzero(~np.isfinite(measured[:, 0]))
    if missing.size:
        predicted = cast(Array, cv2.projectPoints(rest[missing], rvec, tvec, intrinsics.matrix, dist)[0].reshape(-1, 2))
        predicted = _nearest_free_candidates(predicted, candidates.xy, index >= 0,
                                             _pitch_px(rest, rvec, tvec, intrinsics, markers.cols))
        guided = fit_discs(frame, predicted, radius, fixed_radius=radius, edge_px=edge, max_shift=2.0)
        typical = float(np.median(fixed.contrast[fixed.ok])) if fixed.ok.any() else 0.0
        keep = guided.ok & (guided.contrast >= 0.5 * typical)
        measured[missing[keep]] = guided.xy[keep]
    in_pose = np.isfinite(measured[:, 0])
    for _ in range(2):
        have = np.flatnonzero(in_pose)
        rvec, tvec = _pose(rest[have], measured[have], intrinsics, rvec, tvec)
        projected = cv2.projectPoints(rest[have], rvec, tvec, intrinsics.matrix, dist)[0].reshape(-1, 2)
        errors = np.linalg.norm(measured[have] - projected, axis=1)
        off = errors > max(3 * float(np.median(errors)), 1.0)
        if not off.any():
            break
        in_pose[have[off]] = False
    return measured, in_pose, rvec, tvec


def _pitch_px(rest: Array, rvec: Array, tvec: Array, intrinsics: Intrinsics, cols: int) -> float:
    """The lattice pitch in the image (px): the median distance between projected row neighbours."""
    px = cv2.projectPoints(rest, rvec, tvec, intrinsics.matrix, np.asarray(intrinsics.distortion))[0].reshape(-1, cols, 2)
    return float(np.median(np.linalg.norm(np.diff(px, axis=1), axis=2)))


def _nearest_free_candidates(sites_px: Array, candidates_px: Array, taken: npt.NDArray[np.bool_], pitch_px: float) -> Array:
    """Each empty site's start for the guided fit: the nearest candidate no site took, if within
    ``FREE_CANDIDATE_PITCHES`` of the pitch (a marker printed well off its site, too far for the
    association's tolerance), else the site itself. A candidate serves one site at most."""
    out = np.array(sites_px, np.float64)
    free = np.flatnonzero(~taken)
    if not free.size:
        return out
    d = np.linalg.norm(out[:, None, :] - candidates_px[free][None, :, :], axis=2)
    sites_done, cands_done = set(), set()
    for site, cand in zip(*np.unravel_index(np.argsort(d, axis=None), d.shape)):
        if d[site, cand] > FREE_CANDIDATE_PITCHES * pitch_px:
            break
        if site not in sites_done and cand not in cands_done:
            out[site] = candidates_px[free[cand]]
            sites_done.add(site)
            cands_done.add(cand)
    return out


def calibrate_extrinsics(
    recording: str | Path,
    intrinsics: Intrinsics,
    markers: MarkerConfig,
    *,
    nominal_rotvec_rad: tuple[float, float, float] = NOMINAL_ROTVEC_RAD,
    min_fraction: float = 0.8,
) -> ExtrinsicsResult:
    """Solve the gel-to-camera pose from an LED-blink recording (module docstring)."""
    recording = Path(recording)
    with Recording(recording) as rec:
        width, height = sensor_size(rec)
        blinks = find_blinks(rec)
        if not blinks:
            raise CalibrationError(
                f"{recording}: no LED blink found (need at least 1 burst of OFF events next to a burst of ON events); "
                "record the gel at rest while the LED ring switches off and on"
            )
        on, off = accumulate_polarities(rec, blinks, width, height)
    result = extrinsics_from_frame(harmonic_frame(on, off), intrinsics, markers, nominal_rotvec_rad=nominal_rotvec_rad,
                                   min_fraction=min_fraction, source=f"{recording}: ", blinks=len(blinks))
    return replace(result, recording=recording, recording_sha256=sha256_of(recording))


def extrinsics_from_frame(
    frame: Array,
    intrinsics: Intrinsics,
    markers: MarkerConfig,
    *,
    nominal_rotvec_rad: tuple[float, float, float] = NOMINAL_ROTVEC_RAD,
    min_fraction: float = 0.8,
    source: str = "",
    blinks: int = 0,
) -> ExtrinsicsResult:
    """Steps 2-7 of the module docstring on a marker frame (sensor px, markers brighter than the membrane).

    ``source`` prefixes the error messages (the recording's name)."""
    n_markers = markers.rows * markers.cols
    candidates = find_discs(frame, n_markers)
    need = math.ceil(min_fraction * n_markers)
    if len(candidates) < need:
        raise CalibrationError(
            f"{source}{len(candidates)} marker blobs found in {blinks} blink(s), need at least {need} of "
            f"the {markers.rows}x{markers.cols} grid; check the LED blinks and that the markers are in view"
        )
    labels, spurious = associate_grid(candidates.xy, intrinsics, markers.rows, markers.cols,
                                      strength=candidates.strength)
    matched = int((labels[:, 0] >= 0).sum())
    if matched < need:
        raise CalibrationError(
            f"{source}{matched} of {len(candidates)} blobs matched the {markers.rows}x{markers.cols} marker "
            f"grid (need {need}); check the marker rows/cols/pitch in the rig file and the intrinsics"
        )
    measured, in_pose, rvec, tvec = measure_markers(frame, candidates, labels, markers, intrinsics, nominal_rotvec_rad)
    detected = int(in_pose.sum())
    if detected < need:
        raise CalibrationError(
            f"{source}{detected} of {len(candidates)} blobs matched the {markers.rows}x{markers.cols} marker "
            f"grid after fitting (need {need}); check the marker rows/cols/pitch in the rig file and the intrinsics"
        )
    rest = markers.rest_positions_mm()
    projected, _ = cv2.projectPoints(rest, rvec, tvec, intrinsics.matrix, np.asarray(intrinsics.distortion))
    rest_px = cast(Array, projected.reshape(-1, 2))
    errors = np.linalg.norm(measured - rest_px, axis=1)
    camera = CameraModel(intrinsics.fx_px, intrinsics.fy_px, intrinsics.cx_px, intrinsics.cy_px, intrinsics.distortion,
                         tuple(float(v) for v in rvec), tuple(float(v) for v in tvec),  # type: ignore[arg-type]
                         intrinsics.width_px, intrinsics.height_px)
    marker_map = MarkerMap.measure(markers.cols, rest_px, measured, in_pose, camera, rest)
    return ExtrinsicsResult(
        rotvec_rad=rvec.astype(float), translation_mm=tvec.astype(float), rest_gel_mm=rest,
        rest_px=rest_px, measured_px=measured, errors_px=errors, blobs=candidates, spurious=spurious,
        blinks=blinks, frame=frame, markers=markers, in_pose=in_pose, marker_map=marker_map,
    )


def write_extrinsics(result: ExtrinsicsResult, path: str | Path = DEFAULT_EXTRINSICS,
                     intrinsics: Intrinsics | None = None) -> Path:
    """Write ``extrinsics.toml`` (atomically) from a calibration result and the intrinsics it used."""
    path = Path(path)

    body = {
        "rotation_rotvec_rad": [float(v) for v in result.rotvec_rad],
        "rotation_matrix": rotvec_to_matrix(result.rotvec_rad),
        "translation_mm": [float(v) for v in result.translation_mm],
        "reprojection_mean_px": result.mean_error_px,
        "reprojection_std_px": result.std_error_px,
        "reprojection_max_px": result.max_error_px,
        "markers_detected": int(result.detected.sum()),
        "blobs_spurious": result.spurious,
        "blinks": result.blinks,
        "intrinsics_file": str(intrinsics.path) if intrinsics and intrinsics.path else "",
    }
    body.update({"markers_missing": len(result.marker_map.missing_indices),
                 "markers_in_pose": int(result.in_pose.sum())})
    m = result.markers
    markers = {
        "rows": m.rows, "cols": m.cols, "pitch_mm": m.pitch_mm,
        "rest_gel_mm": result.rest_gel_mm,
        "rest_px": result.rest_px,
        "detected": [bool(d) for d in result.detected],
        "error_px": result.errors_px,
    }
    text = (
        "# Gel-to-camera extrinsics (p_cam = R p_gel + t), from `labrig calibrate extrinsics`.\n"
        "# Markers in node order: row-major from -y, -x of the gel frame; rest_px projects rest_gel_mm through the pose;\n"
        "# measured_px, residual_px/mm and error_px are nan where a marker is missing (listed in `missing`).\n"
        f"format_version = {EXTRINSICS_FORMAT_VERSION}\n\n"
        + toml_table("extrinsics", body) + "\n"
        + toml_table("markers", {**markers, **marker_map_table(result.marker_map)})
        + "\n" + toml_table("source", provenance(result.recording, result.recording_sha256))
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    save_text_atomic(path, text)
    return path

