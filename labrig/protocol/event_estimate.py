"""The event sensor's force estimate beside a probing run in virtual time.

:class:`EventEstimator` takes the camera's chunks as a recording would (device time, as they arrive), cuts them
into the pipeline's windows (:class:`~labrig.pipeline.windows.EventWindower`), runs each through the
:class:`~labrig.pipeline.runtime.Pipeline` and publishes its forces into an
:class:`~labrig.protocol.feedback.EstimateFeedback`, stamped with the window's end on the host clock. In virtual
time the pipeline's own computing costs no time: a window's estimate is there when the chunk that closed it
arrives (through the drivers the live pipeline's latency counts). :func:`estimate_pipeline` builds the pipeline
a run uses: the rig's calibration and a depth network, as ``labrig run --live`` does.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from labrig.config import RigConfig
from labrig.devices.camera import EventChunk
from labrig.pipeline import depth_sources, run_setup
from labrig.pipeline.runtime import Pipeline
from labrig.pipeline.windows import DEFAULT_WINDOW_US, EventWindower
from labrig.protocol.feedback import Estimate, EstimateFeedback


def estimate_pipeline(rig: RigConfig, calibration_dir: str | Path | None = None,
                      model: str | Path | None = None) -> Pipeline:
    """The pipeline for ``rig``: its calibration (``calibration_dir``, default the rig file's folder) and the
    depth network ``model`` (default: the newest in models/, else the bundled one), warmed up."""
    folder = rig.path.parent if calibration_dir is None else calibration_dir
    setup = run_setup.setup_for_rig(rig, calibration_dir=folder)
    pipeline = Pipeline(setup, depth_sources.depth_source("model", setup, model_path=model))
    pipeline.warm_up()
    return pipeline


class EventEstimator:
    """Chunks in, estimates out: one pipeline window at a time, published as each window closes.

    ``to_host_ns`` maps the camera's device time (us) to the host clock (ns); ``window_us``: the pipeline's window
    (default: the span the depth source was trained on)."""

    def __init__(self, pipeline: Pipeline, feedback: EstimateFeedback, to_host_ns: Callable[[int], int],
                 window_us: int | None = None) -> None:
        self.pipeline = pipeline
        self.feedback = feedback
        self.to_host_ns = to_host_ns
        self.windower = EventWindower(window_us or round(pipeline.depth.window_us or DEFAULT_WINDOW_US))

    def on_chunk(self, chunk: EventChunk) -> None:
        for window in self.windower.push(chunk.events, chunk.t_host_ns):
            result = self.pipeline.process(window.t0_us, window.t1_us, window.events)
            self.feedback.publish(Estimate(self.to_host_ns(window.t1_us), np.asarray(result.net_force_n, np.float64),
                                           np.asarray(result.forces_n, np.float64),
                                           np.asarray(result.displacement_mm, np.float64)))
