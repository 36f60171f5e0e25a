"""Where a press touched the gel, from the camera's events during it.

The press's events are counted per pixel (ON +1, OFF -1), each pixel is
back-projected to the gel plane through the camera model, and the counts are
fitted with a template centred on the contact: the membrane's brightness
change under the LED ring follows the surface slope, which is axisymmetric
about the contact, so the density of events (markers masked out) is
``a * log(1 + g * slope(|x - c|)) - b`` with the slope profile of the
tabulated contact at the press depth and a, g, b, c fitted. Gel-plane
coordinates in mm, pixels in the camera's sensor.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.interpolate import RegularGridInterpolator
from scipy.optimize import least_squares

from labrig.config import RigConfig
from labrig.errors import CalibrationError
from labrig.physics.camera import CameraModel
from labrig.physics.mechanics import ContactTable

F64 = npt.NDArray[np.float64]

#: Pixels whose gel point is this close to a marker's rest centre are left out of the slope template.
MARKER_MASK_MM = 0.6
#: The template is fitted over this radius around the contact, mm.
TEMPLATE_RADIUS_MM = 8.0
#: Fewest signed events in the gel region a press needs to locate its contact.
MIN_EVENTS = 1000


@dataclass(frozen=True)
class PixelMap:
    """ROI pixels, their rest points on the gel plane (mm) and whether they are clear of the markers."""

    index_of: Callable[[F64, F64], npt.NDArray[np.int64]]
    gel_xy: F64
    clear: npt.NDArray[np.bool_]

    @classmethod
    def build(cls, rig: RigConfig, camera: CameraModel, step: int = 1) -> PixelMap:
        roi = rig.roi
        ys, xs = np.mgrid[roi.y0_px:roi.y1_px:step, roi.x0_px:roi.x1_px:step]
        gel = camera.backproject_to_plane(np.c_[xs.ravel(), ys.ravel()].astype(np.float64))[:, :2]
        m = rig.markers
        fc = gel[:, 0] / m.pitch_mm + (m.cols - 1) / 2
        fr = gel[:, 1] / m.pitch_mm + (m.rows - 1) / 2
        near = np.hypot((fc - np.clip(np.rint(fc), 0, m.cols - 1)) * m.pitch_mm,
                        (fr - np.clip(np.rint(fr), 0, m.rows - 1)) * m.pitch_mm)
        width = xs.shape[1]

        def index_of(x: F64, y: F64) -> npt.NDArray[np.int64]:
            xi, yi = x.astype(np.int64), y.astype(np.int64)
            inside = (xi >= roi.x0_px) & (xi < roi.x1_px) & (yi >= roi.y0_px) & (yi < roi.y1_px)
            inside &= ((xi - roi.x0_px) % step == 0) & ((yi - roi.y0_px) % step == 0)
            out = ((yi - roi.y0_px) // step) * width + (xi - roi.x0_px) // step
            return np.where(inside, out, -1)

        return cls(index_of, gel, near > MARKER_MASK_MM)


@dataclass(frozen=True)
class Located:
    """A contact located in the image: gel-plane centre (mm), template residual (events per pixel), pixels used."""

    xy_mm: F64
    rms: float
    pixels: int
    params: F64


def locate_contact(x: F64, y: F64, polarity: F64, pixels: PixelMap, table: ContactTable, depth_mm: float,
                   guess_mm: npt.ArrayLike) -> Located:
    """The contact centre on the gel plane from the signed event counts of one press (see the module doc);
    ``depth_mm``: the press's depth below the surface, ``guess_mm``: where it was aimed (gel mm)."""
    index = pixels.index_of(x, y)
    ok = index >= 0
    counts = np.bincount(index[ok], polarity[ok], minlength=len(pixels.gel_xy))
    if float(np.abs(counts).sum()) < MIN_EVENTS:
        raise CalibrationError(f"only {int(np.abs(counts).sum())} events in the gel region during the press; "
                               f"at least {MIN_EVENTS} are needed to locate the contact: press deeper or check the camera")
    fields = table.fields(min(max(depth_mm, float(table.depths_mm[1])), float(table.depths_mm[-1])))
    depth = np.asarray(fields.depth_mm, dtype=np.float64)
    gy, gx = np.gradient(depth, fields.y_mm, fields.x_mm)
    slope = RegularGridInterpolator((fields.y_mm, fields.x_mm), np.hypot(gx, gy), bounds_error=False, fill_value=0.0)
    centre = np.asarray(guess_mm, dtype=np.float64).copy()
    # Mean shift on the positive counts first: robust to a guess a few mm off.
    pos = np.clip(counts, 0, None) * pixels.clear
    for _ in range(10):
        near = np.hypot(*(pixels.gel_xy - centre).T) < TEMPLATE_RADIUS_MM * 0.75
        weight = pos[near]
        if weight.sum() <= 0:
            break
        step = (pixels.gel_xy[near] * weight[:, None]).sum(axis=0) / weight.sum() - centre
        centre += step
        if float(np.hypot(*step)) < 0.05:
            break
    use = pixels.clear & (np.hypot(*(pixels.gel_xy - centre).T) < TEMPLATE_RADIUS_MM)
    gel, obs = pixels.gel_xy[use], counts[use]

    def residuals(p: F64) -> F64:
        s = slope((gel[:, 1] - p[1], gel[:, 0] - p[0]))
        return p[2] * np.log1p(p[3] * s) - p[4] - obs

    start = np.r_[centre, max(float(obs.max()), 1.0), 2.0, 0.0]
    result = least_squares(residuals, start, x_scale=np.r_[0.1, 0.1, 1.0, 1.0, 0.1],
                           bounds=(np.r_[-np.inf, -np.inf, 0.0, 0.01, -np.inf], np.r_[np.inf, np.inf, np.inf, 100, np.inf]))
    return Located(result.x[:2].copy(), float(np.sqrt(np.mean(result.fun ** 2))), int(use.sum()), result.x.copy())
