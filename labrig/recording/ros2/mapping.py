"""Recording rows to ROS 2 messages and back, sans-I/O (the message classes come from the type store).

Units and frames follow ROS (REP 103): lengths in metres, forces in newtons, torques in N m, times as
``builtin_interfaces/Time`` (seconds and nanoseconds) on the recording's host clock (the clock its
``t0_host_ns`` counts on: ``stamp = t0_host_ns + 1000 * t_host_us``). labrig's recordings keep
millimetres; the conversion is here and nowhere else.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.recording.ros2 import messages as M

NS_PER_S = 1_000_000_000
NS_PER_US = 1000
MM_PER_M = 1000.0
S_PER_MIN = 60.0
#: A CNC state or a G-code line: ASCII in the recording, UTF-8 strings in ROS; what is not ASCII is replaced.
TEXT_ENCODING = "utf-8"
#: ``t_latest_host_us`` when the latest time of a trigger edge is not known (the recording's int64 max).
UNKNOWN_LATEST_US = np.iinfo(np.int64).max


def host_ns(t0_host_ns: int, t_us: int) -> int:
    """A recording time (host us since its start) on the host clock, ns."""
    return int(t0_host_ns) + int(t_us) * NS_PER_US


def stamp_ns(stamp: Any) -> int:
    """A ``builtin_interfaces/Time`` as integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def time_msg(store: Any, t_ns: int) -> Any:
    """``builtin_interfaces/Time`` for ``t_ns`` (floor division: negative times keep nanosec in 0..1e9)."""
    sec, nanosec = divmod(int(t_ns), NS_PER_S)
    return store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def header(store: Any, t_ns: int, frame_id: str) -> Any:
    return store.types["std_msgs/msg/Header"](stamp=time_msg(store, t_ns), frame_id=frame_id)


def event_packet(store: Any, t_ns: int, frame_id: str, seq: int, width: int, height: int, payload: bytes,
                 encoding: str = "evt3", time_base: int = 0) -> Any:
    """An ``EventPacket``; for ``evt3`` ``time_base`` stays 0, as the Metavision driver leaves it."""
    return store.types[M.EVENT_PACKET](header=header(store, t_ns, frame_id), height=int(height), width=int(width),
                                       seq=int(seq), time_base=int(time_base), encoding=encoding, is_bigendian=False,
                                       events=np.frombuffer(payload, np.uint8))


def vector3(store: Any, xyz: npt.ArrayLike) -> Any:
    x, y, z = (float(v) for v in np.asarray(xyz, dtype=np.float64))
    return store.types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def wrench_stamped(store: Any, t_ns: int, frame_id: str, force_n: npt.ArrayLike, torque_nm: npt.ArrayLike) -> Any:
    """A ``WrenchStamped`` (force N, torque N m, in ``frame_id``'s axes)."""
    wrench = store.types["geometry_msgs/msg/Wrench"](force=vector3(store, force_n), torque=vector3(store, torque_nm))
    return store.types[M.WRENCH_STAMPED](header=header(store, t_ns, frame_id), wrench=wrench)


def pose_stamped(store: Any, t_ns: int, frame_id: str, position_mm: npt.ArrayLike) -> Any:
    """A ``PoseStamped`` at ``position_mm`` (mm in, metres out), orientation identity (the CNC only translates)."""
    x, y, z = (float(v) / MM_PER_M for v in np.asarray(position_mm, dtype=np.float64))
    point = store.types["geometry_msgs/msg/Point"](x=x, y=y, z=z)
    quaternion = store.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    pose = store.types["geometry_msgs/msg/Pose"](position=point, orientation=quaternion)
    return store.types[M.POSE_STAMPED](header=header(store, t_ns, frame_id), pose=pose)


def phase(store: Any, t_start_ns: int, t_end_ns: int, name: str) -> Any:
    return store.types[M.PHASE](header=header(store, t_start_ns, ""), name=name, end=time_msg(store, t_end_ns))


def trigger_edge(store: Any, t_ns: int, polarity: int, t_latest_ns: int | None) -> Any:
    """A ``TriggerEdge``: the earliest host time ``t_ns`` and the latest (None: not known)."""
    return store.types[M.TRIGGER_EDGE](header=header(store, t_ns, ""), polarity=int(polarity),
                                       latest_known=t_latest_ns is not None,
                                       latest=time_msg(store, 0 if t_latest_ns is None else t_latest_ns))


def cnc_status(store: Any, t_ns: int, frame_id: str, state: bytes | str, feed_mm_min: float) -> Any:
    """A ``CncStatus``: the controller's ``state`` as reported and its feed rate (mm/min in, m/s out)."""
    return store.types[M.CNC_STATUS](header=header(store, t_ns, frame_id), state=_text(state),
                                     feed_m_s=float(feed_mm_min) / (MM_PER_M * S_PER_MIN))


def gcode_line(store: Any, t_ns: int, frame_id: str, direction: int, line: bytes | str) -> Any:
    """A ``GcodeLine``: ``direction`` 0 sent to the controller, 1 received from it."""
    return store.types[M.GCODE_LINE](header=header(store, t_ns, frame_id), direction=int(direction), line=_text(line))


def _text(value: bytes | str) -> str:
    return value.decode(TEXT_ENCODING, errors="replace") if isinstance(value, bytes) else str(value)


def string(store: Any, text: str) -> Any:
    return store.types[M.STRING](data=text)


# -- messages to rows ------------------------------------------------------------------------------------


def wrench_values(msg: Any) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(force N, torque N m) of a ``WrenchStamped``."""
    w = msg.wrench
    return (np.array([w.force.x, w.force.y, w.force.z], np.float64),
            np.array([w.torque.x, w.torque.y, w.torque.z], np.float64))


def position_mm(msg: Any) -> npt.NDArray[np.float64]:
    """The position of a ``PoseStamped`` or the translation of a ``TransformStamped``, in mm."""
    p = msg.pose.position if hasattr(msg, "pose") else msg.transform.translation
    return np.array([p.x, p.y, p.z], np.float64) * MM_PER_M


def is_rotated(msg: Any, tolerance: float = 1e-6) -> bool:
    """Whether a pose's orientation is other than the identity (the CNC's tool only translates)."""
    q = msg.pose.orientation if hasattr(msg, "pose") else msg.transform.rotation
    norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    return norm > 0 and abs(abs(q.w) / norm - 1.0) > tolerance


def cnc_status_values(msg: Any) -> tuple[bytes, float]:
    """(state, feed mm/min) of a ``CncStatus``, as the recording's ``cnc`` stream keeps them."""
    return str(msg.state).encode(TEXT_ENCODING), float(msg.feed_m_s) * MM_PER_M * S_PER_MIN


def gcode_values(msg: Any) -> tuple[int, bytes]:
    """(direction, line) of a ``GcodeLine``, as the recording's ``gcode`` stream keeps them."""
    return int(msg.direction), str(msg.line).encode(TEXT_ENCODING)
