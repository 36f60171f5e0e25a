"""Gel-to-camera extrinsics from events of the LED ring blinking, gel at rest.

1. All blinks of the recording are accumulated into one count frame (the gel
   does not move) and the marker blobs get sub-pixel centres
   (:mod:`.eventframes`).
2. Association with the known rows x cols grid, robust to a missing or a
   spurious blob and to the grid's orientation in the image: the centres are
   undistorted with the intrinsics (so the grid is a homography image of the
   plane); the lattice directions come from the nearest-neighbour vectors
   (their angle folded four times, so both axes agree); integer lattice
   coordinates are rounded in that basis from the most central blob, then a
   RANSAC homography from lattice to image re-assigns them three times. Blobs
   further than a quarter pitch from their lattice site are spurious; the
   rows x cols window (either way round) holding most blobs is the grid.
3. A planar grid is symmetric: its 180-degree turn and its mirror images
   (equivalent to viewing the plane from the other side) fit equally well.
   Of the four labellings, the one whose PnP rotation is closest to the
   nominal gel-to-camera rotation is kept (``nominal_rotvec_rad``, the rig
   file's ``[camera] nominal_rotvec_rad``; the reference sensor's camera sits
   below the gel looking up, image x along gel x, image y along gel y).
4. ``cv2.solvePnP`` (iterative) and ``cv2.solvePnPRefineLM`` give the pose;
   the per-marker reprojection errors are reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from labrig.calibration.eventframes import Blobs, accumulate, detect_blobs, find_blinks
from labrig.calibration.files import Intrinsics
from labrig.calibration.intrinsics import CalibrationError, sensor_size, sha256_of
from labrig.config import MarkerConfig
from labrig.frames import rotvec_to_matrix
from labrig.recording import Recording

Array = npt.NDArray[np.float64]

NOMINAL_ROTVEC_RAD = (0.0, 0.0, 0.0)


@dataclass
class ExtrinsicsResult:
    rotvec_rad: Array
    translation_mm: Array
    rest_gel_mm: Array  # (rows*cols, 3), node order row-major from -y, -x
    rest_px: Array  # projections of rest_gel_mm through the fitted pose, (rows*cols, 2)
    measured_px: Array  # detected centres, NaN where a marker was not detected
    errors_px: Array  # per marker |measured - projected|, NaN where not detected
    blobs: Blobs
    spurious: int
    blinks: int
    frame: Array
    markers: MarkerConfig
    recording: Path | None = None
    recording_sha256: str = ""

    @property
    def detected(self) -> npt.NDArray[np.bool_]:
        return np.isfinite(self.errors_px)

    @property
    def mean_error_px(self) -> float:
        return float(np.nanmean(self.errors_px))

    @property
    def std_error_px(self) -> float:
        return float(np.nanstd(self.errors_px))

    @property
    def max_error_px(self) -> float:
        return float(np.nanmax(self.errors_px))


def associate_grid(points_px: Array, intrinsics: Intrinsics, rows: int, cols: int) -> tuple[npt.NDArray[np.int64], int]:
    """For each point, its (row, col) in the grid up to the grid's symmetry, or (-1, -1); and the spurious count.

    The returned labelling has ``cols`` along one lattice axis and ``rows``
    along the other; which way round and which signs are settled by PnP
    against the nominal rotation (:func:`choose_orientation`).
    """
    n = len(points_px)
    labels = np.full((n, 2), -1, np.int64)
    if n < 8:
        return labels, 0
    und = cv2.undistortPoints(points_px.reshape(-1, 1, 2).astype(np.float64), intrinsics.matrix,
                              np.asarray(intrinsics.distortion), P=intrinsics.matrix).reshape(-1, 2)
    from scipy.spatial import cKDTree

    tree = cKDTree(und)
    dist, idx = tree.query(und, k=5)
    vectors = (und[idx[:, 1:]] - und[:, None, :]).reshape(-1, 2)
    lengths = dist[:, 1:].ravel()
    pitch = float(np.median(dist[:, 1]))
    ok = (lengths > 0.7 * pitch) & (lengths < 1.4 * pitch)
    angles = np.arctan2(vectors[ok, 1], vectors[ok, 0])
    theta = float(np.angle(np.mean(np.exp(4j * angles)))) / 4
    basis = np.array([[np.cos(theta), np.sin(theta)], [-np.sin(theta), np.cos(theta)]]) * pitch  # rows: a, b
    seed = und[np.argmin(np.linalg.norm(und - np.median(und, axis=0), axis=1))]
    lattice = np.rint(np.linalg.solve(basis.T, (und - seed).T).T)
    inlier = np.ones(n, bool)
    for _ in range(3):
        h, _ = cv2.findHomography(lattice[inlier], und[inlier], cv2.RANSAC, 0.2 * pitch)
        if h is None:
            return labels, 0
        back = cv2.perspectiveTransform(und.reshape(-1, 1, 2), np.linalg.inv(h)).reshape(-1, 2)
        lattice = np.rint(back)
        inlier = np.linalg.norm(back - lattice, axis=1) < 0.25
    # One point per lattice site: the nearest.
    residual = np.linalg.norm(back - lattice, axis=1)
    order = np.argsort(residual)
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
    best = (-1, 0, 0, 0)  # count, swap, i0, j0
    for swap, (na, nb) in enumerate(((cols, rows), (rows, cols))):
        ia, ib = lat[inlier, 0], lat[inlier, 1]
        for i0 in range(ia.min(), ia.max() - na + 2):
            for j0 in range(ib.min(), ib.max() - nb + 2):
                count = int(((ia >= i0) & (ia < i0 + na) & (ib >= j0) & (ib < j0 + nb)).sum())
                if count > best[0]:
                    best = (count, swap, i0, j0)
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
                best = (angle, index, rvec.ravel(), tvec.ravel())
    if best is None:
        raise CalibrationError("PnP failed for every orientation of the marker grid")
    return best[1], best[2], best[3]


def _marker_sized(blobs: Blobs, n_markers: int) -> Blobs:
    """Blobs within a factor 2.5 of the typical marker area (that of the n_markers largest): noise specks go."""
    if len(blobs) <= n_markers:
        return blobs
    typical = float(np.median(np.sort(blobs.area_px)[-n_markers:]))
    keep = (blobs.area_px > typical / 2.5) & (blobs.area_px < typical * 2.5)
    return Blobs(blobs.xy[keep], blobs.area_px[keep], blobs.radius_px[keep])


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
    n_markers = markers.rows * markers.cols
    with Recording(recording) as rec:
        width, height = sensor_size(rec)
        blinks = find_blinks(rec)
        if not blinks:
            raise CalibrationError(
                f"{recording}: no LED blink found (need at least 1 burst of OFF events next to a burst of ON events); "
                "record the gel at rest while the LED ring switches off and on"
            )
        frame = np.zeros((height, width))
        for blink in blinks:
            frame += accumulate(rec, blink, width, height)
    blobs = _marker_sized(detect_blobs(frame), n_markers)
    need = math.ceil(min_fraction * n_markers)
    if len(blobs) < need:
        raise CalibrationError(
            f"{recording}: {len(blobs)} marker blobs found in {len(blinks)} blink(s), need at least {need} of the "
            f"{markers.rows}x{markers.cols} grid; check the LED blinks and that the markers are in view"
        )
    labels, spurious = associate_grid(blobs.xy, intrinsics, markers.rows, markers.cols)
    matched = int((labels[:, 0] >= 0).sum())
    if matched < need:
        raise CalibrationError(
            f"{recording}: {matched} of {len(blobs)} blobs matched the {markers.rows}x{markers.cols} marker grid "
            f"(need {need}); check the marker rows/cols/pitch in the rig file and the intrinsics"
        )
    index, rvec, tvec = choose_orientation(blobs.xy, labels, markers, intrinsics, nominal_rotvec_rad)
    rest = markers.rest_positions_mm()
    good = index >= 0
    obj = rest[index[good]]
    img = blobs.xy[good]
    dist = np.asarray(intrinsics.distortion)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, intrinsics.matrix, dist, rvec.reshape(3, 1), tvec.reshape(3, 1),
                                      criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    projected, _ = cv2.projectPoints(rest, rvec, tvec, intrinsics.matrix, dist)
    rest_px = projected.reshape(-1, 2)
    measured = np.full((n_markers, 2), np.nan)
    measured[index[good]] = img
    errors = np.linalg.norm(measured - rest_px, axis=1)
    return ExtrinsicsResult(
        rotvec_rad=rvec.ravel().astype(float), translation_mm=tvec.ravel().astype(float), rest_gel_mm=rest,
        rest_px=rest_px, measured_px=measured, errors_px=errors, blobs=blobs, spurious=spurious, blinks=len(blinks),
        frame=frame, markers=markers, recording=recording, recording_sha256=sha256_of(recording),
    )
