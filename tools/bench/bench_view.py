"""The run's animation (``labrig run --view``) against the pipeline run it shows, side by side in one process.

Setup (not timed): a simulated recording as ``make demo`` records one (protocols/demo.toml: 6 mm sphere,
1 mm deep, 0.5 mm shear, probe.toml's 1.5 mm/s, waits of 0.2 s). Timed: the pipeline over the recording (10 ms windows,
the sim's true depth, the view's windows kept by :class:`~labrig.pipeline.view.ViewFrames`), then the
GIF of those windows, matplotlib already imported (its import, about a second, is timed apart: the
command pays it once). Printed: both wall times and their ratio (the target: the view takes no longer
than the run, ratio <= 1), the frames, the GIF's size and the process's peak memory.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import bench_main, emit

from labrig.config import load_rig
from labrig.indenters import load_indenter
from labrig.pipeline import depth_sources, run_setup, runtime
from labrig.pipeline.view import ViewFrames, probing_span_us, write_view
from labrig.recording import Recording
from labrig.sim.live import record_live
from labrig.sim.motion import probing_path


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def run(progress: bool = True) -> dict[str, Any]:
    rig = load_rig()
    sphere = load_indenter("sphere")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sphere.h5"
        if progress:
            print("simulating the recording ...", flush=True)
        tool = probing_path(rig, sphere, depth_mm=1.0, shear_mm=0.5, normal_speed_mm_s=1.5, shear_speed_mm_s=1.5,
                            wait_s=0.2)
        record_live(path, rig, sphere, tool, seed=5, realtime=False)
        with Recording(path) as rec:
            setup = run_setup.setup_for_recording(rec)
            source = depth_sources.depth_source("truth", setup, rec)
            shown = ViewFrames(probing_span_us(rec))
            start = time.perf_counter()
            windows = 0
            for r in runtime.Pipeline(setup, source, keep_sae=True).run(rec, window_us=10_000, concurrent=False):
                windows += 1
                if not shown.offer(r):
                    r.sae = None
            run_s = time.perf_counter() - start
            duration_s = rec.end_us() / 1e6
        gif = Path(tmp) / "view.gif"
        start = time.perf_counter()
        import matplotlib.pyplot  # noqa: F401

        import_s = time.perf_counter() - start
        start = time.perf_counter()
        write_view(shown.frames, setup, gif)
        view_s = time.perf_counter() - start
        size_mb = gif.stat().st_size / 1e6
    return {"recording_s": duration_s, "windows": windows, "frames": len(shown.frames), "run_s": run_s,
            "view_s": view_s, "view_over_run": view_s / run_s, "matplotlib_import_s": import_s, "gif_mb": size_mb,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def render(f: dict[str, Any]) -> None:
    emit("labrig run --view: the animation against the run it shows",
         ["recording s", "windows", "frames", "run s", "view s", "view / run", "import s", "GIF MB", "peak RSS MB"],
         [[f"{f['recording_s']:.1f}", str(f["windows"]), str(f["frames"]), f"{f['run_s']:.1f}", f"{f['view_s']:.1f}",
           f"{f['view_over_run']:.2f}", f"{f['matplotlib_import_s']:.1f}", f"{f['gif_mb']:.1f}", f"{f['peak_rss_mb']:.0f}"]],
         ["view / run: the GIF's wall time over the pipeline's on the same recording (target <= 1)."])


if __name__ == "__main__":
    bench_main(parse_args, run, render)
