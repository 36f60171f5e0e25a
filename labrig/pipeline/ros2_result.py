"""A pipeline result (``labrig run --out``) as a ROS 2 bag: ``labrig export RESULT.h5 --bag OUT.mcap``.

Each window becomes the messages of :mod:`labrig.pipeline.ros2_messages`, stamped (and logged) at the
window's end on the recording's host clock (the result's ``t0_host_ns`` plus the window's end, us). The
depth map goes in where the result kept it (``labrig run --out-depth``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labrig.errors import LabrigError
from labrig.pipeline.results import load_result
from labrig.pipeline.ros2_messages import TOPIC_TYPES, WindowFields, window_messages
from labrig.recording.ros2 import mapping, topics
from labrig.recording.ros2.bagfile import BagWriter

Progress = Callable[[int, int, str], None]


@dataclass(frozen=True)
class ResultExportSummary:
    """What :func:`export_result_bag` wrote: windows, messages, whether depth maps went in, bytes."""

    result: str
    output: str
    windows: int
    markers: int
    messages: int
    depth_maps: bool
    t0_host_ns: int
    output_bytes: int
    elapsed_s: float


def export_result_bag(result: Path, output: Path, *, overwrite: bool = False,
                      progress: Progress | None = None) -> ResultExportSummary:
    """Write the result file ``result`` as a ROS 2 bag in MCAP storage at ``output``."""
    start = time.perf_counter()
    data = load_result(result)
    if "rest_mm" not in data:
        raise LabrigError(f"{result} keeps no marker rest points (written before labrig kept them); "
                          "run `labrig run REC --out` again")
    attrs = data["attrs"]
    t0 = int(attrs.get("t0_host_ns", 0))
    n = int(data["t1_us"].shape[0])
    rest = np.asarray(data["rest_mm"], np.float64)
    depth = data.get("depth_mm")
    with BagWriter(output, overwrite=overwrite) as bag:
        for topic, msgtype in TOPIC_TYPES.items():
            if topic != topics.DEPTH or depth is not None:
                bag.topic(topic, msgtype)
        for i in range(n):
            t_ns = mapping.host_ns(t0, int(data["t1_us"][i]))
            fields = WindowFields(t_ns=t_ns, places_mm=rest + data["displacement_mm"][i], forces_n=data["forces_n"][i],
                                  net_force_n=data["net_force_n"][i], positions_px=data["positions_px"][i],
                                  updated=data["updated"][i].astype(bool), depth_mm=None if depth is None else depth[i])
            for topic, msg in window_messages(bag.store, fields):
                bag.write(topic, t_ns, msg)
            if progress is not None and (i % 64 == 63 or i == n - 1):
                progress(i + 1, n, "windows")
    return ResultExportSummary(result=str(result), output=str(output), windows=n, markers=int(rest.shape[0]),
                               messages=bag.messages, depth_maps=depth is not None, t0_host_ns=t0,
                               output_bytes=bag.bytes_written, elapsed_s=time.perf_counter() - start)
