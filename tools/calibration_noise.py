"""How the camera calibration degrades with event noise: 1x, 4x and 8x the virtual rig's noise.

Records the target and LED-blink scenes at each noise scale (shot noise, leak and
threshold spread multiplied), calibrates intrinsics then extrinsics (with the
recovered intrinsics) and prints each figure against the sim's true camera.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python tools/calibration_noise.py [--views 10] [--seed 0] [--scales 1 4 8]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from labrig.calibration.extrinsics import calibrate_extrinsics
from labrig.calibration.intrinsics import calibrate_intrinsics, intrinsics_from_result
from labrig.config import load_rig
from labrig.errors import CalibrationError
from labrig.frames import rotvec_to_matrix
from labrig.physics.camera import distort_normalized
from labrig.sim.calibration_scenes import record_led_blink, record_target_scene
from labrig.sim.truth_config import true_camera


def figures(scale: float, views: int, seed: int, root: Path) -> dict[str, float]:
    rig = load_rig()
    truth = true_camera(rig)
    target = record_target_scene(root / f"target-{scale}.h5", rig, n_views=views, seed=seed, noise_scale=scale).path
    led = record_led_blink(root / f"led-{scale}.h5", rig, seed=seed, noise_scale=scale).path
    res = calibrate_intrinsics(target)
    intr = intrinsics_from_result(res)
    roi = rig.roi
    u, v = np.meshgrid(np.linspace(roi.x0_px, roi.x1_px - 1, 40), np.linspace(roi.y0_px, roi.y1_px - 1, 40))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    d = distort_normalized(truth.pixels_to_normalized(pixels), intr.distortion)
    mapped = np.stack([truth.fx_px * d[:, 0] + truth.cx_px, truth.fy_px * d[:, 1] + truth.cy_px], axis=1)
    out = {
        "fx_err_pct": 100 * (intr.fx_px / truth.fx_px - 1), "fy_err_pct": 100 * (intr.fy_px / truth.fy_px - 1),
        "cx_err_pct": 100 * (intr.cx_px / truth.cx_px - 1), "cy_err_pct": 100 * (intr.cy_px / truth.cy_px - 1),
        "intrinsics_rms_px": res.rms_px, "views_used": len(res.used), "views": len(res.views),
        "distortion_max_err_px": float(np.linalg.norm(mapped - pixels, axis=1).max()),
    }
    try:
        ext = calibrate_extrinsics(led, intr, rig.markers, nominal_rotvec_rad=rig.camera.nominal_rotvec_rad)
    except CalibrationError as exc:
        print(f"noise x{scale:g}: extrinsics failed: {exc}")
        return out
    r_true, r = truth.gel_to_camera.rotation, rotvec_to_matrix(ext.rotvec_rad)
    t_true = np.asarray(truth.gel_to_camera_translation_mm)
    return {
        **out,
        "rotation_err_deg": float(np.degrees(np.arccos(np.clip((np.trace(r_true.T @ r) - 1) / 2, -1, 1)))),
        "inplane_err_mm": float(np.abs(ext.translation_mm[:2] - t_true[:2]).max()),
        "depth_err_pct": float(100 * (ext.translation_mm[2] / t_true[2] - 1)),
        "reprojection_mean_px": ext.mean_error_px, "reprojection_std_px": ext.std_error_px,
        "markers_detected": float(ext.detected.sum()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 4.0, 8.0])
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        results = {}
        for scale in args.scales:
            start = time.perf_counter()
            results[scale] = figures(scale, args.views, args.seed, Path(tmp))
            print(f"noise x{scale:g}: {time.perf_counter() - start:.1f} s", flush=True)
    keys = list(next(iter(results.values())))
    print(f"{'figure':24s}" + "".join(f"{'x' + format(s, 'g'):>12s}" for s in results))
    for key in keys:
        print(f"{key:24s}" + "".join(f"{results[s].get(key, float('nan')):12.4f}" for s in results))


if __name__ == "__main__":
    main()
