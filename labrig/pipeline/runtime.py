"""The streaming runtime: windows of events through SAE, tracker, depth, displacements and forces.

Windows are fixed in time (``window_us``, 10 ms by default) or in event count
(``window_events``, 20,000 in the paper's evaluation). Per window:

1. front stage: the SAE on the network grid (only when the depth source needs it) and the
   marker tracker;
2. back stage: the depth map from a :class:`DepthSource` (the recording's ``/truth/depth``
   nearest in time, or the ONNX network of :mod:`labrig.pipeline.depthnet`), the markers'
   3D displacements, per-marker forces (the dense surface operator of
   :func:`labrig.pipeline.ifem.build_surface_operator`), net force and contact location.

With ``concurrent=True`` the two stages run in two threads joined by a bounded queue
(window k's forces while window k+1 is tracked), as in the paper; numpy, scipy and
onnxruntime release the GIL in their kernels. ``concurrent=False`` runs them in turn.

The gel modulus is the fitted one (``calibration/gel.toml``) when present, else the rig's;
the camera is the calibrated one (``calibration/intrinsics.toml`` + ``extrinsics.toml``)
when present, else the rig's. :func:`setup_for_recording` resolves both for a recording.
"""

from __future__ import annotations

import json
import queue
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig, load_rig
from labrig.errors import LabrigError
from labrig.physics.camera import CameraModel
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline import displacement, forces, ifem, sae, tracking
from labrig.pipeline.quiet import QuietHold, QuietParams
from labrig.recording import Recording

Array = npt.NDArray[np.float64]

DEFAULT_WINDOW_US = 10_000
PAPER_WINDOW_EVENTS = 20_000
DEFAULT_QUIET = QuietParams()
#: Tiles (rows x columns over the SAE grid) watched for motion with a noise-trained network.
NOISE_TILES = (6, 7)
STAGES = ("read", "sae", "track", "depth", "displacement", "forces")


# -- depth sources -------------------------------------------------------------------------------


class DepthSource(Protocol):
    """Gives the normal-displacement map (90 x 112, mm into the gel) for a window.

    ``window_us``: the span the source's SAE covers, ending at the pipeline window's end
    (None: the pipeline window itself). ``depth_mm`` gets that span's SAE (None unless
    ``needs_sae``), its bounds and how many events fell in it.
    """

    name: str
    needs_sae: bool
    window_us: float | None

    def depth_mm(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                 n_events: int) -> npt.NDArray[np.float32]: ...


class TruthDepth:
    """The recording's ``/truth/depth`` map nearest in time to the window's end (virtual rig only)."""

    name = "truth"
    needs_sae = False
    window_us: float | None = None

    def __init__(self, recording: Recording) -> None:
        if "truth/depth" not in recording.streams or recording.rows("truth/depth") == 0:
            raise LabrigError(f"{recording.path}: no /truth/depth (only virtual-rig recordings have it); use --depth model")
        self.t_us = recording.column("truth/depth", "t_host_us")
        self.maps = np.asarray(recording.column("truth/depth", "depth_mm"), np.float32)  # ~40 kB per solve, loaded once

    def index(self, t_us: int) -> int:
        k = int(np.searchsorted(self.t_us, t_us))
        if k == 0:
            return 0
        if k >= len(self.t_us):
            return len(self.t_us) - 1
        return k if self.t_us[k] - t_us < t_us - self.t_us[k - 1] else k - 1

    def depth_mm(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                 n_events: int = 0) -> npt.NDArray[np.float32]:
        return self.maps[self.index(t1_us)]


class ModelDepth:
    """The depth network (:class:`labrig.pipeline.depthnet.DepthModel`, ONNX) on the SAE of the
    window it was trained on (model card ``window_ms``) ending at each pipeline window's end.

    ``path``: an ``.onnx`` with its card, or a bundled network's name (``default``,
    ``noise-robust``). ``quiet``: windows at the noise floor keep the last active map
    (:mod:`labrig.pipeline.quiet`); ``"auto"`` also watches each SAE tile for motion when the
    network was trained with background-noise augmentation (:func:`quiet_params_for`); None
    feeds every window to the network.
    """

    needs_sae = True

    def __init__(self, path: str | Path, threads: int = 1, quiet: QuietParams | str | None = "auto") -> None:
        from labrig.models import model_path
        from labrig.pipeline.depthnet import DepthModel

        self.model = DepthModel(model_path(path), threads=threads)
        self.name = f"model:{self.model.name}"
        self.window_us: float | None = self.model.window_ms * 1000.0
        if quiet == "auto":
            quiet = quiet_params_for(self.model.card)
        assert not isinstance(quiet, str), f"quiet must be QuietParams, None or 'auto', not {quiet!r}"
        self.hold = QuietHold(GRID_SHAPE, quiet) if quiet is not None else None

    def depth_mm(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                 n_events: int) -> npt.NDArray[np.float32]:
        assert sae_grid is not None
        if self.hold is None:
            return self.model.depth_mm(sae_grid)
        if self.hold(n_events, t1_us - t0_us, sae_grid):
            return self.hold.held_mm
        return self.hold.update(self.model.depth_mm(sae_grid))


def quiet_params_for(card: dict[str, Any]) -> QuietParams:
    """The quiet-window gate for a network: the rate gate, plus per-tile activity when it was
    trained on noisy windows. A network trained clean draws dimples from a noisy SAE, so
    the more sensitive tile test would hand it more of them (measured in docs/evaluation.md)."""
    noise_trained = bool((card.get("augmentation") or {}).get("background_noise"))
    return replace(DEFAULT_QUIET, tiles=NOISE_TILES) if noise_trained else DEFAULT_QUIET


def default_model_path(folder: str | Path = "models") -> Path:
    """The newest ``*.onnx`` with a model card in ``folder`` (your own trained networks), else the bundled one."""
    from labrig.models import bundled_model_path

    candidates = sorted(Path(folder).glob("*.onnx"), key=lambda p: p.stat().st_mtime)
    candidates = [p for p in candidates if p.with_suffix(".json").exists()]
    return candidates[-1] if candidates else bundled_model_path()


# -- windows -------------------------------------------------------------------------------------


def windows(recording: Recording, *, window_us: int | None = DEFAULT_WINDOW_US, window_events: int | None = None,
            start_us: int = 0, end_us: int | None = None, read_us: int = 50_000
            ) -> Iterator[tuple[int, int, npt.NDArray[Any]]]:
    """(t0_us, t1_us, events) per window: fixed time, or fixed event count (t1 = the next window's first event).

    Count windows read ahead in ``read_us`` slices and drop the final partial window.
    """
    end = recording.end_us() if end_us is None else int(end_us)
    if (window_us is None) == (window_events is None):
        raise ValueError("give exactly one of window_us and window_events")
    if window_us is not None:
        if window_us <= 0:
            raise ValueError("window_us must be positive")
        for t0 in range(int(start_us), end, int(window_us)):
            t1 = min(t0 + int(window_us), end)
            yield t0, t1, recording.events_between(t0, t1)
        return
    assert window_events is not None
    if window_events <= 0:
        raise ValueError("window_events must be positive")
    buffer: list[npt.NDArray[Any]] = []
    held = 0
    t = int(start_us)
    while t < end:
        chunk = recording.events_between(t, min(t + read_us, end))
        t += read_us
        if len(chunk):
            buffer.append(chunk)
            held += len(chunk)
        while held >= window_events:
            events = np.concatenate(buffer) if len(buffer) > 1 else buffer[0]
            window, rest = events[:window_events], events[window_events:]
            t0 = int(window["t"][0])
            t1 = int(rest["t"][0]) if len(rest) else int(window["t"][-1]) + 1
            yield t0, t1, window
            buffer, held = ([rest] if len(rest) else []), len(rest)


# -- the pipeline --------------------------------------------------------------------------------


@dataclass
class WindowResult:
    """One window's output. Forces are on the gel (pressing: Fz < 0), gel frame, N."""

    index: int
    t0_us: int
    t1_us: int
    n_events: int
    positions_px: Array  # (M, 2) tracked marker centres
    updated: npt.NDArray[np.bool_]  # (M,)
    displacement_mm: Array  # (M, 3)
    forces_n: Array  # (M, 3)
    net_force_n: Array  # (3,)
    contact_px: Array  # (2,), nan without contact
    contact_mm: Array  # (2,), nan without contact
    depth_mm: npt.NDArray[np.float32]  # (90, 112)
    sae: npt.NDArray[np.float32] | None = None  # (2, 90, 112) when computed
    seconds: dict[str, float] = field(default_factory=dict)  # per-stage processing time


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


class Pipeline:
    """The stages for one sensor; :meth:`process` runs one window, :meth:`run` streams a recording."""

    def __init__(self, setup: PipelineSetup, depth: DepthSource, *,
                 tracker_params: tracking.TrackerParams | None = None,
                 surface_params: ifem.SurfaceParams | None = None, normal_mode: str = "contact",
                 threshold_mm: float = 0.01, keep_sae: bool = False, cache_dir: str | Path | None = None) -> None:
        self.setup = setup
        self.depth = depth
        rig = setup.rig
        params = tracker_params or tracking.TrackerParams(marker_diameter_px=tracking.marker_diameter_px(rig))
        self.tracker = tracking.Tracker(setup.rest_px, params)
        base = surface_params or ifem.SurfaceParams()
        from dataclasses import replace

        self.surface_params = replace(base, youngs_modulus_mpa=setup.youngs_modulus_mpa,
                                      poisson_ratio=setup.poisson_ratio)
        self.operator = ifem.build_surface_operator(rig, self.surface_params, cache_dir=cache_dir)
        self.surface = forces.SurfaceForces(self.operator, setup.camera, rig.roi, GRID_SHAPE)
        self.rest_mm = rig.markers.rest_positions_mm()
        self.normal_mode = normal_mode
        self.threshold_mm = threshold_mm
        self.keep_sae = keep_sae
        self._index = 0
        self._recent: list[npt.NDArray[Any]] = []  # events of the depth source's window

    # The two stages (each returns the state the next one needs).

    def front(self, t0_us: int, t1_us: int, events: npt.NDArray[Any], read_s: float = 0.0) -> dict[str, Any]:
        """SAE (if needed) and tracking.

        Each window gets its own SAE array (80 kB): with the stages in two threads the front
        runs up to two windows ahead of the back stage, which must still see its window's SAE."""
        seconds = {"read": read_s}
        grid = None
        start = time.perf_counter()
        d0_us, d_events = self._depth_window(t0_us, t1_us, events)
        if self.depth.needs_sae or self.keep_sae:
            grid = sae.sae_grid(d_events, d0_us, t1_us, self.setup.rig.roi)
        seconds["sae"] = time.perf_counter() - start
        start = time.perf_counter()
        positions, updated = self.tracker.update(events)
        seconds["track"] = time.perf_counter() - start
        state = {"index": self._index, "t0": t0_us, "t1": t1_us, "n": len(events), "sae": grid,
                 "d0": d0_us, "d_n": len(d_events),
                 "positions": positions.copy(), "updated": updated.copy(), "seconds": seconds}
        self._index += 1
        return state

    def back(self, state: dict[str, Any]) -> WindowResult:
        """Depth, displacements, forces, net force and contact location."""
        seconds = state["seconds"]
        start = time.perf_counter()
        depth = self.depth.depth_mm(state["sae"], state["d0"], state["t1"], state["d_n"])
        seconds["depth"] = time.perf_counter() - start
        start = time.perf_counter()
        u = displacement.displacements_mm(state["positions"], depth, self.setup.camera, self.rest_mm,
                                          self.setup.rig.roi, sample_px=self.setup.rest_px)
        seconds["displacement"] = time.perf_counter() - start
        start = time.perf_counter()
        f = self.surface(depth, u, self.normal_mode, self.threshold_mm)
        f *= forces.stiffening_factor(depth, self.setup.rig.gel.thickness_mm, self.setup.stiffening)
        where = forces.contact_location(depth, self.setup.rig.roi, self.setup.camera, self.threshold_mm)
        seconds["forces"] = time.perf_counter() - start
        nan2 = np.full(2, np.nan)
        return WindowResult(state["index"], state["t0"], state["t1"], state["n"], state["positions"], state["updated"],
                            u, f, forces.net_force_n(f), where.position_px if where else nan2,
                            where.position_mm if where else nan2, depth,
                            state["sae"] if self.keep_sae else None, seconds)

    def _depth_window(self, t0_us: int, t1_us: int, events: npt.NDArray[Any]) -> tuple[int, npt.NDArray[Any]]:
        """(start, events) of the depth source's window ending at ``t1_us``.

        Windows shorter than the source's (count windows in a fast press) reach back into the
        events of earlier windows, kept here; longer ones (count windows at rest) are cut."""
        span = self.depth.window_us
        if span is None:
            return t0_us, events
        d0 = round(t1_us - span)
        self._recent.append(events)
        while len(self._recent) > 1 and (len(self._recent[0]) == 0 or int(self._recent[0]["t"][-1]) < d0):
            self._recent.pop(0)
        held = np.concatenate(self._recent) if len(self._recent) > 1 else self._recent[0]
        first = int(np.searchsorted(held["t"], d0))
        self._recent = [held[first:]]
        return d0, self._recent[0]

    def process(self, t0_us: int, t1_us: int, events: npt.NDArray[Any]) -> WindowResult:
        return self.back(self.front(t0_us, t1_us, events))

    def run(self, recording: Recording, *, window_us: int | None = DEFAULT_WINDOW_US, window_events: int | None = None,
            start_us: int = 0, end_us: int | None = None, concurrent: bool = True,
            on_result: Callable[[WindowResult], None] | None = None) -> Iterator[WindowResult]:
        """Stream ``recording`` through the pipeline, yielding each window's result in order.

        ``window_events`` (if given) replaces the default time windows."""
        if window_events is not None:
            window_us = None
        source = windows(recording, window_us=window_us, window_events=window_events, start_us=start_us, end_us=end_us)

        def timed() -> Iterator[tuple[int, int, npt.NDArray[Any], float]]:
            while True:
                start = time.perf_counter()
                try:
                    t0, t1, ev = next(source)
                except StopIteration:
                    return
                yield t0, t1, ev, time.perf_counter() - start

        if not concurrent:
            for t0, t1, ev, read_s in timed():
                result = self.back(self.front(t0, t1, ev, read_s))
                if on_result is not None:
                    on_result(result)
                yield result
            return
        states: queue.Queue[Any] = queue.Queue(maxsize=2)
        done = object()
        failure: list[BaseException] = []
        stop = threading.Event()

        def producer() -> None:
            try:
                for t0, t1, ev, read_s in timed():
                    if stop.is_set():
                        break
                    states.put(self.front(t0, t1, ev, read_s))
            except BaseException as exc:  # handed to the consumer
                failure.append(exc)
            finally:
                states.put(done)

        thread = threading.Thread(target=producer, name="labrig-pipeline-front", daemon=True)
        thread.start()
        try:
            while True:
                state = states.get()
                if state is done:
                    break
                result = self.back(state)
                if on_result is not None:
                    on_result(result)
                yield result
        finally:
            stop.set()
            while thread.is_alive():  # unblock the producer if it waits on a full queue
                try:
                    states.get_nowait()
                except queue.Empty:
                    thread.join(0.01)
            thread.join()
        if failure:
            raise failure[0]


# -- configuration from a recording ---------------------------------------------------------------


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
                        calibration_dir: str | Path | None = "calibration",
                        youngs_modulus_mpa: float | None = None, poisson_ratio: float | None = None,
                        stiffening: float | None = None) -> PipelineSetup:
    """Rig, camera, rest pixels and gel modulus for ``recording``.

    Rig: ``rig``, else the one the recording carries, else calibration/rig.toml. Files: those
    the recording names, else ``calibration_dir`` (None: none); then as :func:`setup_for_rig`.
    """
    rig = rig or rig_from_recording(recording) or load_rig()
    return setup_for_rig(rig, calibration_dir=calibration_dir, youngs_modulus_mpa=youngs_modulus_mpa,
                         poisson_ratio=poisson_ratio, stiffening=stiffening, named=_named_calibration(recording))


def setup_for_rig(rig: RigConfig, *, calibration_dir: str | Path | None = "calibration",
                  youngs_modulus_mpa: float | None = None, poisson_ratio: float | None = None,
                  stiffening: float | None = None, named: dict[str, Path] | None = None) -> PipelineSetup:
    """Camera, rest pixels and gel law for ``rig`` (a live stream, or a recording's rig).

    Files: ``named`` ({file name: path}) first, else ``calibration_dir`` (None: none). Modulus
    and stiffening: the arguments, else gel.toml, else the rig's [gel] modulus and a linear gel
    (stiffening 0). Camera: intrinsics.toml + extrinsics.toml, else the rig's.
    """
    from labrig.calibration.files import camera_from_calibration, load_extrinsics, load_intrinsics

    sources: dict[str, str] = {"rig": str(rig.path)}
    files = dict(named or {})
    if calibration_dir is not None:
        for name in ("gel.toml", "intrinsics.toml", "extrinsics.toml"):
            candidate = Path(calibration_dir) / name
            if name not in files and candidate.exists():
                files[name] = candidate
    e, nu, b = rig.gel.youngs_modulus_mpa, rig.gel.poisson_ratio, 0.0
    sources["modulus"], sources["stiffening"] = "rig [gel]", "linear gel"
    if "gel.toml" in files and (youngs_modulus_mpa is None or stiffening is None):
        from labrig.calibration.gel import load_gel

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
    camera, rest_px = CameraModel.from_rig(rig), None
    sources["camera"] = "rig"
    if "intrinsics.toml" in files and "extrinsics.toml" in files:
        extrinsics = load_extrinsics(files["extrinsics.toml"])
        camera = camera_from_calibration(load_intrinsics(files["intrinsics.toml"]), extrinsics)
        rest_px = np.asarray(extrinsics.rest_px, np.float64)
        sources["camera"] = f"{files['intrinsics.toml']} + {files['extrinsics.toml']}"
    if rest_px is None:
        rest_px = camera.project(rig.markers.rest_positions_mm())
    return PipelineSetup(rig, camera, rest_px, e, nu, sources, stiffening=b)


def depth_source(kind: str, recording: Recording, model_path: str | Path | None = None, threads: int = 1) -> DepthSource:
    """"truth" (the recording's /truth/depth) or "model" (the ONNX network, newest in models/ by default)."""
    if kind == "truth":
        return TruthDepth(recording)
    if kind == "model":
        return ModelDepth(model_path or default_model_path(), threads=threads)
    raise LabrigError(f"depth source must be 'truth' or 'model', not {kind!r}")


# -- result files --------------------------------------------------------------------------------

RESULT_FORMAT = "labrig.forces"
RESULT_VERSION = 1


class ResultWriter:
    """Per-window force fields into an HDF5 file (datasets grow one row per window).

    Rows are buffered and written ``FLUSH_ROWS`` at a time (one HDF5 chunk; a row at a time
    costs about 6 ms, more than the pipeline's own work per window); :meth:`close` writes the rest.
    """

    FLUSH_ROWS = 64

    FIELDS: tuple[tuple[str, str, tuple[int, ...], str], ...] = (
        ("t0_us", "<i8", (), "us"), ("t1_us", "<i8", (), "us"), ("n_events", "<i8", (), ""),
        ("positions_px", "<f4", ("M", 2), "px"), ("updated", "u1", ("M",), ""),
        ("displacement_mm", "<f4", ("M", 3), "mm"), ("forces_n", "<f4", ("M", 3), "N"),
        ("net_force_n", "<f8", (3,), "N"), ("contact_px", "<f8", (2,), "px"), ("contact_mm", "<f8", (2,), "mm"),
        ("processing_s", "<f8", (), "s"),
    )

    def __init__(self, path: str | Path, n_markers: int, attrs: dict[str, Any], depth: bool = False) -> None:
        import h5py

        self.path = Path(path)
        self.file = h5py.File(self.path, "w")
        self.file.attrs["format"] = RESULT_FORMAT
        self.file.attrs["format_version"] = RESULT_VERSION
        for key, value in attrs.items():
            self.file.attrs[key] = value
        self.n = 0
        self._pending: list[dict[str, Any]] = []
        for name, dtype, shape, unit in self.FIELDS:
            dims = tuple(n_markers if d == "M" else d for d in shape)
            ds = self.file.create_dataset(name, shape=(0, *dims), maxshape=(None, *dims), dtype=dtype,
                                          chunks=(64, *dims), compression="gzip" if dims else None)
            ds.attrs["unit"] = unit
        if depth:
            ds = self.file.create_dataset("depth_mm", shape=(0, *GRID_SHAPE), maxshape=(None, *GRID_SHAPE),
                                          dtype="<f4", chunks=(8, *GRID_SHAPE), compression="gzip")
            ds.attrs["unit"] = "mm"

    def write(self, r: WindowResult) -> None:
        values = {"t0_us": r.t0_us, "t1_us": r.t1_us, "n_events": r.n_events, "positions_px": r.positions_px,
                  "updated": r.updated, "displacement_mm": r.displacement_mm, "forces_n": r.forces_n,
                  "net_force_n": r.net_force_n, "contact_px": r.contact_px, "contact_mm": r.contact_mm,
                  "processing_s": sum(r.seconds.values())}
        if "depth_mm" in self.file:
            values["depth_mm"] = r.depth_mm
        self._pending.append(values)
        if len(self._pending) >= self.FLUSH_ROWS:
            self.flush()

    def flush(self) -> None:
        """Write the buffered rows."""
        if not self._pending:
            return
        rows, self._pending = self._pending, []
        for name in rows[0]:
            ds = self.file[name]
            ds.resize(self.n + len(rows), axis=0)
            ds[self.n:] = np.stack([np.asarray(row[name]) for row in rows])
        self.n += len(rows)

    def close(self) -> None:
        self.flush()
        self.file.attrs["windows"] = self.n
        self.file.close()

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def load_result(path: str | Path) -> dict[str, Any]:
    """A result file as {dataset: array} plus ``attrs``."""
    import h5py

    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != RESULT_FORMAT:
            raise LabrigError(f"{path}: not a labrig force result file")
        out: dict[str, Any] = {name: f[name][()] for name in f}
        out["attrs"] = {k: (v.item() if hasattr(v, "item") else v) for k, v in f.attrs.items()}
    return out
