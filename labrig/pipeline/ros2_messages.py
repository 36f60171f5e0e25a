"""One window of the pipeline's output as ROS 2 messages, sans-I/O (for a bag and for the live view).

* ``/labrig/force_field``: ``sensor_msgs/msg/PointCloud2``, one point per marker: ``x, y, z`` (float32,
  m) its place in the gel frame (rest point plus displacement), ``fx, fy, fz`` (float32, N) the force on
  the gel there;
* ``/labrig/net_force``: ``geometry_msgs/msg/WrenchStamped`` in the gel frame: the summed force (N) and its
  moment about the gel frame's origin (N m, from the markers' places and forces);
* ``/labrig/depth``: ``sensor_msgs/msg/Image``, ``32FC1``, the depth map on the network grid, mm;
* ``/labrig/tracks``: ``sensor_msgs/msg/PointCloud2`` in the camera frame: ``u, v`` (float32, sensor px)
  each marker's tracked centre, ``updated`` (float32, 1 where the window moved it).

Every message is stamped at the window's end on the stream's host clock (ns).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.recording.ros2 import mapping, topics
from labrig.recording.ros2 import messages as M

MM_PER_M = 1000.0
FLOAT32 = 7  # sensor_msgs/PointField FLOAT32


@dataclass(frozen=True)
class WindowFields:
    """What one window gives the messages. Gel frame for places (mm) and forces (N); sensor px for tracks."""

    t_ns: int
    places_mm: npt.NDArray[np.float64]  # (M, 3) rest point + displacement
    forces_n: npt.NDArray[np.float64]  # (M, 3) force on the gel
    net_force_n: npt.NDArray[np.float64]  # (3,)
    positions_px: npt.NDArray[np.float64]  # (M, 2)
    updated: npt.NDArray[np.bool_]  # (M,)
    depth_mm: npt.NDArray[np.float32] | None = None  # (90, 112)


def point_cloud(store: Any, t_ns: int, frame_id: str, columns: dict[str, npt.NDArray[Any]]) -> Any:
    """A ``PointCloud2`` of one row of points, a float32 field per column (every column of one length)."""
    names = list(columns)
    n = len(next(iter(columns.values())))
    packed = np.empty((n, len(names)), "<f4")
    for i, name in enumerate(names):
        packed[:, i] = columns[name]
    field_type = store.types[M.POINT_FIELD]
    fields = [field_type(name=name, offset=4 * i, datatype=FLOAT32, count=1) for i, name in enumerate(names)]
    return store.types[M.POINT_CLOUD2](
        header=mapping.header(store, t_ns, frame_id), height=1, width=n, fields=fields, is_bigendian=False,
        point_step=4 * len(names), row_step=4 * len(names) * n, data=packed.reshape(-1).view(np.uint8),
        is_dense=bool(np.isfinite(packed).all()))


def depth_image(store: Any, t_ns: int, depth_mm: npt.NDArray[np.float32]) -> Any:
    """A ``32FC1`` image of the depth map (mm), row-major, little-endian."""
    depth = np.ascontiguousarray(depth_mm, "<f4")
    height, width = depth.shape
    return store.types[M.IMAGE](header=mapping.header(store, t_ns, topics.GEL_FRAME), height=height, width=width,
                                encoding="32FC1", is_bigendian=0, step=4 * width, data=depth.reshape(-1).view(np.uint8))


def window_messages(store: Any, w: WindowFields) -> list[tuple[str, Any]]:
    """(topic, message) for one window: force field, net force, tracks and, where given, the depth map."""
    places_m = np.asarray(w.places_mm, np.float64) / MM_PER_M
    forces = np.asarray(w.forces_n, np.float64)
    field = point_cloud(store, w.t_ns, topics.GEL_FRAME, {
        "x": places_m[:, 0], "y": places_m[:, 1], "z": places_m[:, 2],
        "fx": forces[:, 0], "fy": forces[:, 1], "fz": forces[:, 2]})
    moment = np.nansum(np.cross(places_m, forces), axis=0)
    net = mapping.wrench_stamped(store, w.t_ns, topics.GEL_FRAME, w.net_force_n, moment)
    tracks = point_cloud(store, w.t_ns, topics.CAMERA_FRAME, {
        "u": w.positions_px[:, 0], "v": w.positions_px[:, 1], "updated": np.asarray(w.updated, np.float32)})
    out = [(topics.FORCE_FIELD, field), (topics.NET_FORCE, net), (topics.TRACKS, tracks)]
    if w.depth_mm is not None:
        out.append((topics.DEPTH, depth_image(store, w.t_ns, w.depth_mm)))
    return out


#: The type of each topic :func:`window_messages` writes.
TOPIC_TYPES = {topics.FORCE_FIELD: M.POINT_CLOUD2, topics.NET_FORCE: M.WRENCH_STAMPED, topics.TRACKS: M.POINT_CLOUD2,
               topics.DEPTH: M.IMAGE}


def point_cloud_columns(msg: Any) -> dict[str, npt.NDArray[np.float32]]:
    """A float32 ``PointCloud2`` (as :func:`point_cloud` writes it) back to its columns."""
    names = [f.name for f in msg.fields]
    data = np.asarray(msg.data, np.uint8).view("<f4").reshape(int(msg.width) * int(msg.height), len(names))
    return {name: data[:, i] for i, name in enumerate(names)}
