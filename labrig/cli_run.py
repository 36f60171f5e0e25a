"""``labrig run REC`` / ``labrig run --live``: stream a recording, or the rig's camera, through the
inference pipeline and write the force fields.

Mount on the main app with :func:`add_run_commands` (``cli.py``). The live path is in
:mod:`labrig.cli_run_live` (its work in :mod:`labrig.live`). User errors are
:class:`LabrigError` s, printed as one line by ``labrig``.
"""

from __future__ import annotations

import json
import time
from array import array
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from labrig.errors import LabrigError

console = Console()
err_console = Console(stderr=True)


def run(
    recording: Annotated[Path | None, typer.Argument(help="A recording (.h5); or --live.")] = None,
    live: Annotated[bool, typer.Option("--live", help=(
        "Stream the camera of the rig file's \\[devices] instead of a recording; with a probing run "
        "(--indenter/--protocol, always on the embedded virtual rig) for as long as the run lasts."))] = False,
    seconds: Annotated[float | None, typer.Option(help="--live, camera only: stop after this long (default: Ctrl-C).")] = None,
    indenter: Annotated[str | None, typer.Option(help="--live: run one probing run with this indenter meanwhile.")] = None,
    protocol: Annotated[Path | None, typer.Option(
        help="--live: the probing run's protocol (default protocols/probe.toml).")] = None,
    at: Annotated[str | None, typer.Option("--at", help="--live: the probing run's contact location X,Y, gel mm.")] = None,
    depth_mm: Annotated[float | None, typer.Option(help="--live: the probing run's depth below contact, mm.")] = None,
    save_recording: Annotated[Path | None, typer.Option(
        help="--live: keep the probing run's recording here (.h5; default: compared with, then deleted).")] = None,
    max_lag_ms: Annotated[float | None, typer.Option(
        help="--live: skip depth and forces of windows older than this, ms (default 100; tracking goes on).")] = None,
    window_ms: Annotated[float | None, typer.Option(
        help="Fixed-time windows, ms (default 10; live: the network's trained window).")] = None,
    window_events: Annotated[int | None, typer.Option(help="Fixed-count windows (the paper's evaluation: 20000).")] = None,
    depth: Annotated[str | None, typer.Option(
        help="Depth source: truth (the recording's /truth/depth; the default for REC) or model (ONNX; live).")] = None,
    model: Annotated[Path | None, typer.Option(
        help="Depth network: an .onnx with its card, or a bundled one (default, noise-robust); "
             "default: newest in models/, else bundled.")] = None,
    out: Annotated[Path | None, typer.Option(help="Result file (.h5): per-window markers, displacements, forces.")] = None,
    view: Annotated[Path | None, typer.Option(help="Animation (.gif): SAE, tracks, depth, x/y/normal force maps.")] = None,
    view_every: Annotated[int, typer.Option(help="Every n-th window in the animation.")] = 3,
    calibration: Annotated[Path | None, typer.Option(
        help="Folder with gel.toml, intrinsics.toml, extrinsics.toml (default: calibration/ if present; live: the rig "
             "file's folder).")] = None,
    rig_path: Annotated[Path | None, typer.Option("--rig", help=(
        "Rig TOML (default: the one stored in the recording; live: calibration/rig.toml)."))] = None,
    youngs_modulus_mpa: Annotated[float | None, typer.Option(
        help="Gel modulus, MPa (default: gel.toml, else the rig's).")] = None,
    serial: Annotated[bool, typer.Option(help="Run the stages in turn instead of in two threads.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the summary as JSON (stable keys, units in names).")] = False,
) -> None:
    """Stream RECORDING (or the live camera) through SAE, tracker, depth, iFEM; per-window forces into
    --out, an animation into --view."""
    from labrig.config import load_rig
    from labrig.pipeline import depth_sources, results, run_setup, runtime
    from labrig.pipeline.windows import WindowSpec
    from labrig.recording import Recording

    if live:
        if recording is not None:
            raise LabrigError(f"give a recording ({recording}) or --live, not both")
        if serial:
            raise LabrigError("--serial applies to a recording; the live pipeline always runs its two stages in two threads")
        from labrig.cli_run_live import LiveOptions, run_live

        run_live(LiveOptions(window_ms, window_events, depth, model, out, view, view_every, calibration, rig_path,
                             youngs_modulus_mpa, seconds, indenter, protocol, at, depth_mm, save_recording, max_lag_ms,
                             as_json))
        return
    if recording is None:
        raise LabrigError("give a recording (labrig run REC) or --live (the rig's camera)")
    live_only = {"--seconds": seconds, "--indenter": indenter, "--protocol": protocol, "--at": at, "--depth-mm": depth_mm,
                 "--save-recording": save_recording, "--max-lag-ms": max_lag_ms}
    if given := [flag for flag, value in live_only.items() if value is not None]:
        raise LabrigError(f"{', '.join(given)} only apply to --live; drop them to run a recording")
    depth = depth or "truth"
    windows = WindowSpec.from_options(window_ms, window_events)
    if view is not None and view.suffix.lower() != ".gif":
        raise LabrigError("--view writes a GIF: give a path ending in .gif")
    if not recording.exists():
        raise LabrigError(f"{recording}: no such recording")
    window_us = windows.window_us
    frames: list[runtime.WindowResult] = []
    with Recording(recording) as rec:
        setup = run_setup.setup_for_recording(
            rec, rig=load_rig(rig_path) if rig_path else None,
            calibration_dir=calibration if calibration is not None else Path("calibration"),
            youngs_modulus_mpa=youngs_modulus_mpa)
        source = depth_sources.depth_source(depth, rec, model)
        pipe = runtime.Pipeline(setup, source, keep_sae=view is not None)
        attrs = {"recording": str(recording), "depth_source": source.name, "window_us": window_us or 0,
                 "window_events": window_events or 0, "youngs_modulus_mpa": setup.youngs_modulus_mpa,
                 "poisson_ratio": setup.poisson_ratio, "sources": json.dumps(setup.sources)}
        writer = results.ResultWriter(out, len(setup.rest_px), attrs) if out is not None else None
        start = time.perf_counter()
        log = WindowLog()
        try:
            for r in pipe.run(rec, window_us=window_us, window_events=window_events, concurrent=not serial):
                if writer is not None:
                    writer.write(r)
                if view is not None and r.index % max(view_every, 1) == 0:
                    frames.append(r)
                r.sae = None if view is None or r.index % max(view_every, 1) else r.sae
                log.add(r)
        finally:
            if writer is not None:
                writer.close()
        wall = time.perf_counter() - start
    if not len(log):
        raise LabrigError(f"{recording}: no windows (no events?)")
    summary = window_summary(str(recording), log, wall, source.name, setup, window_us, window_events, out, view)
    if view is not None:
        write_view(frames, setup, view)
    if as_json:
        print(json.dumps(summary, indent=2))
    else:
        _print(summary)


class WindowLog:
    """What the summary needs of each window, 8 bytes a value (a live run may last hours): times (us),
    event count, net force (N, on the gel) and each stage's seconds."""

    def __init__(self) -> None:
        self.t0_us, self.t1_us, self.n_events = array("q"), array("q"), array("q")
        self.net_force_n = array("d")
        self.stage_s: dict[str, array[float]] = {}

    def add(self, r: Any) -> None:
        self.t0_us.append(r.t0_us)
        self.t1_us.append(r.t1_us)
        self.n_events.append(r.n_events)
        self.net_force_n.extend(float(v) for v in r.net_force_n)
        for name, seconds in r.seconds.items():
            self.stage_s.setdefault(name, array("d", [0.0] * (len(self.t0_us) - 1))).append(seconds)

    def __len__(self) -> int:
        return len(self.t0_us)

    def net(self) -> np.ndarray:
        """(W, 3) N."""
        return np.asarray(self.net_force_n).reshape(-1, 3)


def window_summary(recording: str | None, log: WindowLog, wall: float, depth: str, setup: Any, window_us: int | None,
                   window_events: int | None, out: Path | None, view: Path | None) -> dict[str, Any]:
    """The run's summary (stable keys, units in names)."""
    t0, t1, net = np.asarray(log.t0_us), np.asarray(log.t1_us), log.net()
    busy = np.sum([np.asarray(v) for v in log.stage_s.values()], axis=0)
    stages = {k: float(np.median(v) * 1000) for k, v in log.stage_s.items()}
    k = int(np.argmin(net[:, 2]))
    return {
        "recording": recording, "depth_source": depth, "windows": len(log),
        "window_us": window_us, "window_events": window_events, "duration_s": float((t1[-1] - t0[0]) / 1e6),
        "wall_s": wall, "processing_per_window_ms": float(np.median(busy) * 1000),
        "real_time_factor": float(np.median(busy / np.maximum(t1 - t0, 1) * 1e6)),
        "stage_median_ms": stages, "youngs_modulus_mpa": setup.youngs_modulus_mpa, "sources": setup.sources,
        "peak_normal_force_n": float(-net[k, 2]) + 0.0, "peak_at_us": int(t1[k]),
        "peak_net_force_n": [float(v) for v in net[k]], "out": str(out) if out else None, "view": str(view) if view else None,
    }


def stage_table(stage_median_ms: dict[str, float], title: str | None = None) -> Table:
    """The per-stage median latencies (ms) as a rich table."""
    table = Table(title=title)
    table.add_column("stage")
    table.add_column("median ms", justify="right")
    for name, ms in stage_median_ms.items():
        table.add_row(name, f"{ms:.3f}")
    return table


def _print(s: dict[str, Any]) -> None:
    console.print(stage_table(s["stage_median_ms"], f"labrig run {Path(s['recording']).name} ({s['depth_source']} depth)"))
    mode = f"{s['window_events']} events" if s["window_events"] else f"{s['window_us'] / 1000:g} ms"
    console.print(f"{s['windows']} windows of {mode} over {s['duration_s']:.2f} s in {s['wall_s']:.2f} s; "
                  f"processing {s['processing_per_window_ms']:.2f} ms per window (real-time factor "
                  f"{s['real_time_factor']:.2f})")
    f = s["peak_net_force_n"]
    console.print(f"peak normal force {s['peak_normal_force_n']:.2f} N at {s['peak_at_us'] / 1e6:.3f} s "
                  f"(net {f[0]:+.2f}, {f[1]:+.2f}, {f[2]:+.2f} N); E = {s['youngs_modulus_mpa']:.3g} MPa "
                  f"from {escape(s['sources']['modulus'])}; camera: {escape(s['sources']['camera'])}")
    for key in ("out", "view"):
        if s[key]:
            console.print(f"{key}: {s[key]}")


def _marker_grid(values: np.ndarray, rows: int, cols: int) -> np.ndarray:
    return values.reshape(rows, cols)


def write_view(frames: list[Any], setup: Any, path: Path, fps: float = 10.0) -> Path:
    """A GIF like the paper's figure 1: SAE, marker tracks, depth, then x, y and normal force per marker."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

    if not frames:
        raise LabrigError("nothing to animate")
    rig = setup.rig
    rows, cols = rig.markers.rows, rig.markers.cols
    roi = rig.roi
    extent_px = (roi.x0_px, roi.x1_px, roi.y1_px, roi.y0_px)
    fmax = max(float(np.abs(f.forces_n).max()) for f in frames) or 1.0
    shear_max = max(float(np.abs(f.forces_n[:, :2]).max()) for f in frames) or 1.0
    dmax = max(float(f.depth_mm.max()) for f in frames) or 1.0
    fig, axes = plt.subplots(2, 3, figsize=(11, 6.2), constrained_layout=True)
    (ax_sae, ax_track, ax_depth), (ax_fx, ax_fy, ax_fz) = axes
    first = frames[0]

    def sae_rgb(f: Any) -> np.ndarray:
        s = np.zeros((*f.depth_mm.shape, 3), np.float32)
        if f.sae is not None:
            s[..., 0], s[..., 2] = f.sae[1], f.sae[0]  # ON red, OFF blue
        return s

    im_sae = ax_sae.imshow(sae_rgb(first), extent=extent_px, interpolation="nearest")
    ax_sae.set_title("SAE (ON red, OFF blue)")
    rest = setup.rest_px
    ax_track.scatter(rest[:, 0], rest[:, 1], s=4, c="0.7")
    tracks = ax_track.scatter(first.positions_px[:, 0], first.positions_px[:, 1], s=6, c="k")
    quiver = ax_track.quiver(rest[:, 0], rest[:, 1], *(first.positions_px - rest).T * 5, angles="xy",
                             scale_units="xy", scale=1, color="tab:red", width=0.004)
    ax_track.set_xlim(roi.x0_px, roi.x1_px)
    ax_track.set_ylim(roi.y1_px, roi.y0_px)
    ax_track.set_aspect("equal")
    ax_track.set_title("marker tracks (shift x5)")
    im_depth = ax_depth.imshow(first.depth_mm, extent=extent_px, cmap="viridis", vmin=0, vmax=dmax)
    ax_depth.set_title("depth, mm")
    fig.colorbar(im_depth, ax=ax_depth, shrink=0.8)
    maps = []
    for ax, comp, title, vmax, cmap in ((ax_fx, 0, "Fx, N", shear_max, "RdBu_r"), (ax_fy, 1, "Fy, N", shear_max, "RdBu_r"),
                                        (ax_fz, 2, "normal force -Fz, N", fmax, "magma")):
        values = -first.forces_n[:, 2] if comp == 2 else first.forces_n[:, comp]
        im = ax.imshow(_marker_grid(values, rows, cols), cmap=cmap, vmin=0 if comp == 2 else -vmax, vmax=vmax,
                       origin="upper", interpolation="nearest")
        ax.set_title(title)
        fig.colorbar(im, ax=ax, shrink=0.8)
        maps.append((im, comp))
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    title = fig.suptitle("")

    def update(i: int) -> list[Any]:
        f = frames[i]
        im_sae.set_data(sae_rgb(f))
        tracks.set_offsets(f.positions_px)
        quiver.set_UVC(*(f.positions_px - rest).T * 5)
        im_depth.set_data(f.depth_mm)
        for im, comp in maps:
            values = -f.forces_n[:, 2] if comp == 2 else f.forces_n[:, comp]
            im.set_data(_marker_grid(values, rows, cols))
        n = f.net_force_n
        title.set_text(f"t = {f.t1_us / 1e6:.3f} s   net force ({n[0]:+.2f}, {n[1]:+.2f}, {n[2]:+.2f}) N")
        return [im_sae, tracks, quiver, im_depth, title, *(m for m, _ in maps)]

    anim = FuncAnimation(fig, update, frames=len(frames), blit=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    anim.save(str(path), writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path


def add_run_commands(app: typer.Typer) -> None:
    """Mount ``run`` on the main app."""
    app.command("run")(run)
