"""Camera intrinsics from events of a blinking dot-grid target (OpenCV pinhole, k1 k2 p1 p2 [k3]).

1. Blinks are found from event-rate bursts (:mod:`.eventframes`); each gives a
   count frame. Consecutive blinks whose blobs coincide (median distance
   under 1 px) are one view of the target; their frames are summed.
2. Blobs get sub-pixel centres; the grid is associated with OpenCV's
   ``findCirclesGrid`` (symmetric grid) run on a clean image of discs drawn
   at the blob centres, and each grid point takes the sub-pixel centre of its
   blob. Views whose grid is not found whole (target partly off the sensor,
   missing dots) are rejected.
3. ``cv2.calibrateCamera`` solves the model (k3 fixed at 0 unless asked);
   views whose RMS reprojection error exceeds ``max(3 x median, max_view_rms_px)``
   are dropped and the model is solved again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from labrig.cache import sha256_of
from labrig.calibration.eventframes import Blobs, accumulate, detect_blobs, find_blinks
from labrig.calibration.files import DEFAULT_INTRINSICS, Intrinsics, provenance, save_text_atomic, toml_table
from labrig.errors import CalibrationError
from labrig.physics.target import DotGridTarget
from labrig.recording import Recording

Array = npt.NDArray[np.float64]


@dataclass
class TargetView:
    """One view: its blinks' time span, the summed frame's blobs and, if the grid was found, its points."""

    index: int
    t0_us: int
    t1_us: int
    blinks: int
    blobs: Blobs
    image_points: Array | None = None
    rejected: str = ""
    rms_px: float = float("nan")


@dataclass
class IntrinsicsResult:
    camera_matrix: Array
    distortion: Array  # k1 k2 p1 p2 k3
    width_px: int
    height_px: int
    rms_px: float
    views: list[TargetView]
    used: list[int]
    object_points: Array
    rvecs: list[Array] = field(default_factory=list)
    tvecs: list[Array] = field(default_factory=list)
    fix_k3: bool = True
    recording: Path | None = None
    recording_sha256: str = ""
    preview: Array | None = None  # the frame of the first used view (for plots)

    @property
    def per_view_rms_px(self) -> list[float]:
        return [self.views[i].rms_px for i in self.used]

    def residuals(self, view: int) -> tuple[Array, Array]:
        """(measured points, reprojected points) of a used view, px."""
        k = self.used.index(view)
        projected, _ = cv2.projectPoints(self.object_points, self.rvecs[k], self.tvecs[k], self.camera_matrix, self.distortion)
        image_points = self.views[view].image_points
        assert image_points is not None
        return image_points, cast(Array, projected.reshape(-1, 2))


def target_from_recording(rec: Recording) -> DotGridTarget | None:
    """The target geometry a recording names in its ``extra_target_*`` metadata (None if it names none)."""
    attrs = rec.attrs
    if "extra_target_rows" not in attrs:
        return None
    return DotGridTarget(rows=int(attrs["extra_target_rows"]), cols=int(attrs["extra_target_cols"]),
                         pitch_mm=float(attrs["extra_target_pitch_mm"]),
                         dot_diameter_mm=float(attrs.get("extra_target_dot_diameter_mm", 0.8)))


def sensor_size(rec: Recording) -> tuple[int, int]:
    """(width, height) of the sensor from the recording's rig TOML (EVK4 default 1280 x 720)."""
    import tomllib

    try:
        camera = tomllib.loads(str(rec.attrs.get("rig", ""))).get("camera", {})
        return int(camera.get("width_px", 1280)), int(camera.get("height_px", 720))
    except tomllib.TOMLDecodeError:
        return 1280, 720


def find_grid(blobs: Blobs, rows: int, cols: int, width: int, height: int) -> Array | None:
    """Sub-pixel grid points (rows*cols, 2) in the target's row-major order, or None if the grid is not found whole."""
    if len(blobs) < rows * cols:
        return None
    tree_d = _nearest_distances(blobs.xy)
    radius = int(max(3, min(0.3 * float(np.median(tree_d)), 25)))
    canvas = np.full((height, width), 255, np.uint8)
    for x, y in blobs.xy:
        cv2.circle(canvas, (int(np.rint(x * 16)), int(np.rint(y * 16))), radius * 16, 0, -1, shift=4)
    params = cv2.SimpleBlobDetector_Params()  # type: ignore[attr-defined]  # cv2 stubs: the legacy alias is missing
    params.minArea = 0.5 * np.pi * radius**2
    params.maxArea = 2.0 * np.pi * radius**2
    params.filterByConvexity = params.filterByInertia = False
    detector = cv2.SimpleBlobDetector_create(params)  # type: ignore[attr-defined]  # cv2 stubs: the legacy alias is missing
    for flags in (cv2.CALIB_CB_SYMMETRIC_GRID, cv2.CALIB_CB_SYMMETRIC_GRID | cv2.CALIB_CB_CLUSTERING):
        found, centres = cv2.findCirclesGrid(canvas, (cols, rows), flags=flags, blobDetector=detector)
        if found:
            break
    if not found or centres is None or len(centres) != rows * cols:
        return None
    centres = centres.reshape(-1, 2).astype(np.float64)
    d = np.linalg.norm(centres[:, None, :] - blobs.xy[None, :, :], axis=2)
    nearest = d.argmin(axis=1)
    if np.any(d[np.arange(len(centres)), nearest] > 2.0) or len(set(nearest.tolist())) != len(nearest):
        return None
    return blobs.xy[nearest]


def _nearest_distances(xy: Array) -> Array:
    from scipy.spatial import cKDTree

    d, _ = cKDTree(xy).query(xy, k=2)
    return d[:, 1]


def _same_view(a: Blobs, b: Blobs) -> bool:
    if len(a) == 0 or len(b) == 0 or abs(len(a) - len(b)) > 0.1 * max(len(a), len(b)):
        return False
    from scipy.spatial import cKDTree

    d, _ = cKDTree(a.xy).query(b.xy)
    return bool(np.median(d) < 1.0)


def collect_views(rec: Recording, width: int, height: int) -> tuple[list[TargetView], list[Array]]:
    """Views of the target (consecutive coinciding blinks summed) and their frames."""
    views: list[TargetView] = []
    frames: list[Array] = []
    for blink in find_blinks(rec):
        frame = accumulate(rec, blink, width, height)
        blobs = detect_blobs(frame)
        if views and _same_view(views[-1].blobs, blobs):
            frames[-1] = frames[-1] + frame
            last = views[-1]
            views[-1] = TargetView(last.index, last.t0_us, blink.t1_us, last.blinks + 1, detect_blobs(frames[-1]))
            continue
        views.append(TargetView(len(views), blink.t0_us, blink.t1_us, 1, blobs))
        frames.append(frame)
    return views, frames


def calibrate_intrinsics(
    recording: str | Path,
    target: DotGridTarget | None = None,
    *,
    fix_k3: bool = True,
    min_views: int = 6,
    max_view_rms_px: float = 1.0,
) -> IntrinsicsResult:
    """Calibrate the camera from a recording of a blinking dot-grid target (module docstring)."""
    recording = Path(recording)
    with Recording(recording) as rec:
        target = target or target_from_recording(rec) or DotGridTarget()
        width, height = sensor_size(rec)
        views, frames = collect_views(rec, width, height)
    rows, cols = target.rows, target.cols
    if not views:
        raise CalibrationError(
            f"{recording}: no blink found (0 bursts of one polarity); record the target while its dots blink "
            "(on/off at each pose, held still)"
        )
    for view in views:
        view.image_points = find_grid(view.blobs, rows, cols, width, height)
        if view.image_points is None:
            view.rejected = f"grid not found ({len(view.blobs)} blobs, need {rows}x{cols} = {rows * cols})"
    found = [v.index for v in views if v.image_points is not None]
    if len(found) < min_views:
        raise CalibrationError(
            f"{recording}: the {cols}x{rows} target grid was found in {len(found)} of {len(views)} views; "
            f"need at least {min_views}. Record more poses with the whole target on the sensor, or give the "
            "right target size (--rows/--cols)"
        )
    object_points = target.points_mm().astype(np.float32)
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    used = found
    for _ in range(3):
        rms, matrix, dist, rvecs, tvecs = _solve(object_points, [views[i].image_points for i in used], width, height, flags)
        for i, rvec, tvec in zip(used, rvecs, tvecs):
            projected, _ = cv2.projectPoints(object_points, rvec, tvec, matrix, dist)
            image_points = views[i].image_points
            assert image_points is not None
            err = projected.reshape(-1, 2) - image_points
            views[i].rms_px = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
        errors = np.array([views[i].rms_px for i in used])
        limit = max(3.0 * float(np.median(errors)), max_view_rms_px)
        keep = [i for i, e in zip(used, errors) if e <= limit]
        if len(keep) == len(used):
            break
        for i in set(used) - set(keep):
            views[i].rejected = f"reprojection RMS {views[i].rms_px:.2f} px > {limit:.2f} px"
        if len(keep) < min_views:
            raise CalibrationError(
                f"{recording}: only {len(keep)} views fit the model within {limit:.2f} px (need {min_views}); "
                "the target may have moved during its blinks, or the target size is wrong"
            )
        used = keep
    return IntrinsicsResult(
        camera_matrix=matrix, distortion=dist.ravel()[:5].astype(np.float64), width_px=width, height_px=height,
        rms_px=float(rms), views=views, used=used, object_points=object_points.astype(np.float64),
        rvecs=[np.asarray(r, float).ravel() for r in rvecs], tvecs=[np.asarray(t, float).ravel() for t in tvecs],
        fix_k3=fix_k3, recording=recording, recording_sha256=sha256_of(recording), preview=frames[used[0]],
    )


def _solve(object_points: npt.NDArray[np.float32], image_points: list[Array | None], width: int, height: int,
           flags: int) -> tuple[float, Array, Array, list[Array], list[Array]]:
    obj = [object_points] * len(image_points)
    img = [np.asarray(p, np.float32).reshape(-1, 1, 2) for p in image_points]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, matrix, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, (width, height), None, None, flags=flags,
                                                          criteria=criteria)
    return float(rms), cast(Array, matrix), cast(Array, dist), cast(list[Array], list(rvecs)), cast(list[Array], list(tvecs))


def write_intrinsics(result: IntrinsicsResult, path: str | Path = DEFAULT_INTRINSICS) -> Path:
    """Write ``intrinsics.toml`` (atomically) from a calibration result."""
    path = Path(path)
    k = result.camera_matrix
    body = {
        "fx_px": float(k[0, 0]), "fy_px": float(k[1, 1]), "cx_px": float(k[0, 2]), "cy_px": float(k[1, 2]),
        "camera_matrix_px": np.asarray(k, float),
        "distortion": [float(d) for d in result.distortion],
        "k3_fixed": result.fix_k3,
        "width_px": result.width_px, "height_px": result.height_px,
        "rms_px": result.rms_px,
        "n_views": len(result.used),
        "n_views_rejected": sum(1 for v in result.views if v.rejected),
        "views_used": list(result.used),
        "per_view_rms_px": result.per_view_rms_px,
    }
    text = (
        "# Camera intrinsics (OpenCV pinhole, distortion = [k1, k2, p1, p2, k3]), from `labrig calibrate intrinsics`.\n"
        + toml_table("intrinsics", body, {"distortion": "k1 k2 p1 p2 k3", "views_used": "view indices in the recording"})
        + "\n" + toml_table("source", provenance(result.recording, result.recording_sha256))
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    save_text_atomic(path, text)
    return path


def intrinsics_from_result(result: IntrinsicsResult, path: Path | None = None) -> Intrinsics:
    """The camera intrinsics a calibration result gives (as :func:`~labrig.calibration.files.load_intrinsics` reads them back)."""
    k = result.camera_matrix
    return Intrinsics(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                      tuple(float(d) for d in result.distortion),  # type: ignore[arg-type]
                      result.width_px, result.height_px, result.rms_px, len(result.used), path)
