"""The animated view of a pipeline run (``labrig run --view``): a GIF like the paper's figure 1.

Each frame: the window's SAE, the marker tracks, the depth map, then the x, y and normal force
per marker (N, on the gel, gel frame). :class:`ViewFrames` picks the windows: those in the
probing phases, thinned to at most :data:`MAX_VIEW_FRAMES` as they come, so memory stays
bounded however long the recording. The figure is laid out once; each frame updates its
artists, is drawn once (matplotlib's Agg, imported when a view is written) and is kept as a
palette image (one byte per pixel, one palette for the whole animation).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from labrig.errors import LabrigError
from labrig.pipeline.run_setup import PipelineSetup
from labrig.pipeline.runtime import WindowResult
from labrig.recording import Recording

#: The most frames an animation keeps (its windows are thinned to fit).
MAX_VIEW_FRAMES = 200
#: Recording time between an animation's frames by default (us): at 10 frames per second, real time.
VIEW_FRAME_US = 100_000
#: Margin (us) around the probing phases (Normal Down to Normal Up) that the animation shows.
VIEW_MARGIN_US = 300_000
#: The phases an animation shows by default (the recording's probing sequence).
VIEW_PHASES = ("normal_down", "wait", "shear", "shear_opposite", "normal_up")


def probing_span_us(recording: Recording) -> tuple[int, int] | None:
    """Host-time span (us) of the recording's probing phases with :data:`VIEW_MARGIN_US` either side,
    or None (no phases: the whole recording)."""
    if "phases" not in recording.streams or recording.rows("phases") == 0:
        return None
    probing = [p for p in recording.phases() if p.name in VIEW_PHASES]
    if not probing:
        return None
    return (min(p.t_start_us for p in probing) - VIEW_MARGIN_US, max(p.t_end_us for p in probing) + VIEW_MARGIN_US)


class ViewFrames:
    """The windows an animation shows: those ending inside ``span_us`` (None: all), every ``every``-th
    (None: one per :data:`VIEW_FRAME_US` of recording), thinned as they come to at most ``max_frames``:
    when twice that many are kept, every other one is dropped and the stride doubles, so at most
    ``2 * max_frames`` are ever held."""

    def __init__(self, span_us: tuple[int, int] | None = None, every: int | None = None,
                 max_frames: int = MAX_VIEW_FRAMES) -> None:
        if max_frames < 1 or (every is not None and every < 1):
            raise LabrigError("an animation needs at least one frame, and --view-every at least 1")
        self.span_us = span_us
        self.stride = every or 1
        self.by_time = every is None
        self.max_frames = max_frames
        self._kept: list[WindowResult] = []
        self._seen = 0
        self._next_us: int | None = None

    def offer(self, result: WindowResult) -> bool:
        """Keep ``result`` if the animation shows it (the caller may drop its SAE otherwise)."""
        if self.span_us is not None and not self.span_us[0] <= result.t1_us <= self.span_us[1]:
            return False
        if self.by_time:
            if self._next_us is not None and result.t1_us < self._next_us:
                return False
            self._next_us = result.t1_us + VIEW_FRAME_US
        self._seen += 1
        if (self._seen - 1) % self.stride:
            return False
        self._kept.append(result)
        if len(self._kept) >= 2 * self.max_frames:
            self._kept = self._kept[::2]
            self.stride *= 2
        return True

    @property
    def frames(self) -> list[WindowResult]:
        """The windows kept, thinned to at most ``max_frames``."""
        step = -(-len(self._kept) // self.max_frames) if self._kept else 1
        return self._kept[::step]


def _marker_grid(values: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Per-marker values (M,) as the marker grid (rows, cols), row-major as the rig numbers them."""
    return values.reshape(rows, cols)


def write_view(frames: Sequence[WindowResult], setup: PipelineSetup, path: Path, fps: int = 10, dpi: int = 72,
               progress: Callable[[int, int], None] | None = None) -> Path:
    """A GIF like the paper's figure 1: SAE, marker tracks, depth, then x, y and normal force per marker.

    ``progress(done, total)`` is called after each frame is drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    if not frames:
        raise LabrigError("nothing to animate")
    fig, update, moving = _figure(frames, setup, dpi)
    for artist in moving:
        artist.set_animated(True)
    fig.canvas.draw()  # the constrained layout, once, and the still parts: axes, colour bars, labels
    fig.set_layout_engine("none")
    background = fig.canvas.copy_from_bbox(fig.bbox)  # type: ignore[attr-defined]
    font = _font(dpi)

    def render(frame: WindowResult) -> Image.Image:
        fig.canvas.restore_region(background)  # type: ignore[attr-defined]
        update(frame)
        for artist in moving:
            fig.draw_artist(artist)
        image = Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3])  # type: ignore[attr-defined]
        _caption(image, frame, font)
        return image

    palette = _palette([render(frames[k]) for k in {0, len(frames) // 2, len(frames) - 1}])
    images: list[Image.Image] = []
    try:
        for i, frame in enumerate(frames):
            images.append(render(frame).quantize(palette=palette, dither=Image.Dither.NONE))
            if progress is not None:
                progress(i + 1, len(frames))
    finally:
        plt.close(fig)
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
    return path


def _font(dpi: int) -> Any:
    """The caption's font: Pillow's own (scalable where FreeType is present), about 12 pt at ``dpi``."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=max(8, round(12 * dpi / 72)))
    except TypeError:  # Pillow without FreeType: its fixed bitmap font
        return ImageFont.load_default()


def _caption(image: Any, frame: WindowResult, font: Any) -> None:
    """The window's time and net force, drawn centred at the top of its frame (cheaper than a figure title)."""
    from PIL import ImageDraw

    n = frame.net_force_n
    text = f"t = {frame.t1_us / 1e6:.3f} s   net force on the gel ({n[0]:+.2f}, {n[1]:+.2f}, {n[2]:+.2f}) N, gel frame"
    draw = ImageDraw.Draw(image)
    width = draw.textlength(text, font=font)
    draw.text(((image.width - width) / 2, 2), text, fill=(0, 0, 0), font=font)


def _palette(samples: list[Any]) -> Any:
    """One 256-colour palette for the animation, from sample frames (PIL images) side by side."""
    from PIL import Image

    width, height = samples[0].width, samples[0].height
    strip = Image.new("RGB", (width * len(samples), height))
    for k, image in enumerate(samples):
        strip.paste(image, (k * width, 0))
    return strip.quantize(colors=256, method=Image.Quantize.FASTOCTREE)


def _figure(frames: Sequence[WindowResult], setup: PipelineSetup,
            dpi: int) -> tuple[Any, Callable[[WindowResult], None], list[Any]]:
    """The figure for ``frames`` (colour scales over all of them), the function that shows one frame, and
    the artists it changes."""
    import matplotlib.pyplot as plt

    rig = setup.rig
    rows, cols = rig.markers.rows, rig.markers.cols
    roi = rig.roi
    extent_px = (roi.x0_px, roi.x1_px, roi.y1_px, roi.y0_px)
    fmax = max(float(np.abs(f.forces_n).max()) for f in frames) or 1.0
    shear_max = max(float(np.abs(f.forces_n[:, :2]).max()) for f in frames) or 1.0
    dmax = max(float(f.depth_mm.max()) for f in frames) or 1.0
    fig, axes = plt.subplots(2, 3, figsize=(11, 6.2), dpi=dpi, constrained_layout=True)
    (ax_sae, ax_track, ax_depth), (ax_fx, ax_fy, ax_fz) = axes
    first = frames[0]

    def sae_rgb(f: WindowResult) -> np.ndarray:
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
    im_depth = ax_depth.imshow(first.depth_mm, extent=extent_px, cmap="viridis", vmin=0, vmax=dmax,
                               interpolation="nearest")
    ax_depth.set_title("depth, mm")
    fig.colorbar(im_depth, ax=ax_depth, shrink=0.8)
    maps = []
    for ax, comp, label, vmax, cmap in ((ax_fx, 0, "Fx on the gel, N", shear_max, "RdBu_r"),
                                        (ax_fy, 1, "Fy on the gel, N", shear_max, "RdBu_r"),
                                        (ax_fz, 2, "normal force -Fz on the gel, N", fmax, "magma")):
        values = -first.forces_n[:, 2] if comp == 2 else first.forces_n[:, comp]
        im = ax.imshow(_marker_grid(values, rows, cols), cmap=cmap, vmin=0 if comp == 2 else -vmax, vmax=vmax,
                       origin="upper", interpolation="nearest")
        ax.set_title(label)
        fig.colorbar(im, ax=ax, shrink=0.8)
        maps.append((im, comp))
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(" ")  # room for the caption, which is drawn on each frame's image (:func:`_caption`)

    def update(f: WindowResult) -> None:
        im_sae.set_data(sae_rgb(f))
        tracks.set_offsets(f.positions_px)
        quiver.set_UVC(*(f.positions_px - rest).T * 5)
        im_depth.set_data(f.depth_mm)
        for im, comp in maps:
            values = -f.forces_n[:, 2] if comp == 2 else f.forces_n[:, comp]
            im.set_data(_marker_grid(values, rows, cols))

    update(first)
    return fig, update, [im_sae, tracks, quiver, im_depth, *(m for m, _ in maps)]
