"""The ROS 2 message definitions labrig reads and writes, and the type store that knows them.

The standard messages (``std_msgs``, ``geometry_msgs``, ``sensor_msgs``) come with rosbags' ROS 2
Humble store. ``event_camera_msgs/msg/EventPacket`` is not in it: its ``.msg`` text below is the
package's own, verbatim. labrig's messages of its own (a protocol phase, a trigger edge sent to the
camera, the CNC controller's status report and its G-code conversation) have no standard equivalent; they
are defined here in the same ``.msg`` language, so any MCAP reader (Foxglove, ``ros2 bag``) decodes them
from the schema the bag carries. ``tf2_msgs/msg/TFMessage`` (``/tf``) is read, never written.
"""

from __future__ import annotations

from functools import cache
from typing import Any

from labrig.errors import LabrigError

#: The line a missing optional dependency gives.
INSTALL_HINT = "pip install 'labrig[ros2]'"

EVENT_PACKET = "event_camera_msgs/msg/EventPacket"
#: ``msg_ros2/EventPacket.msg`` of ros-event-camera/event_camera_msgs (Apache-2.0), verbatim. For the
#: ``evt3`` encoding the Metavision driver leaves ``time_base`` 0 ("not used for evt3"): the sensor time
#: is in the EVT 3.0 words, a stream that continues from one packet to the next; the header stamp is the
#: host time the packet's first buffer arrived. For ``mono`` and ``trigger`` an event's sensor time is
#: ``time_base`` + its 32-bit ``dt``, in nanoseconds.
EVENT_PACKET_MSG = """\
# This message contains a packet of camera events

std_msgs/Header header     # standard ROS header
uint32 height     # image height
uint32 width      # image width

uint64 seq        # sequence number to detect lost messages
uint64 time_base  # event ros time = time_base + decoded event_time
string encoding   # the encoding scheme to use
bool is_bigendian # true if machine stores in big endian format

uint8[] events
"""

PHASE = "labrig_msgs/msg/Phase"
#: A protocol phase of a labrig probing run (the recording's ``phases`` stream): an interval on the
#: recording's host clock.
PHASE_MSG = """\
# A protocol phase of a labrig probing run: an interval on the recording's host clock.
std_msgs/Header header       # stamp: the host time the phase began
string name                  # the phase (approach, press, wait, shear, retract, ...)
builtin_interfaces/Time end  # the host time the phase ended
"""

TRIGGER_EDGE = "labrig_msgs/msg/TriggerEdge"
#: A trigger edge another device sent to the camera (the recording's ``trigger_out`` stream).
TRIGGER_EDGE_MSG = """\
# A trigger edge sent to the camera's trigger input by another device (e.g. a CNC output).
std_msgs/Header header          # stamp: the earliest host time the edge can have happened
uint8 polarity                  # 1 rising, 0 falling
bool latest_known               # false: the latest time is not known
builtin_interfaces/Time latest  # the latest host time the edge can have happened
"""

CNC_STATUS = "labrig_msgs/msg/CncStatus"
#: A status report of the CNC's controller (the recording's ``cnc`` stream less the position, which
#: ``/cnc/pose`` carries as a standard PoseStamped at the same stamp).
CNC_STATUS_MSG = """\
# A status report of the CNC's controller (GRBL's answer to '?'), as labrig records it.
std_msgs/Header header  # stamp: the host time the report was received; frame_id: the machine frame
string state            # the controller's state as reported: Idle, Run, Jog, Hold:0, Hold:1, Alarm, Door:0, Home, Check, Sleep
float64 feed_m_s        # the current feed rate, m/s (GRBL reports mm/min); NaN: not reported
"""

GCODE_LINE = "labrig_msgs/msg/GcodeLine"
#: A line of the conversation with the CNC's controller (the recording's ``gcode`` stream): the moves
#: commanded and the controller's answers.
GCODE_LINE_MSG = """\
# A line of the G-code conversation with the CNC's controller: a command sent, or the controller's answer.
std_msgs/Header header  # stamp: the host time the line was sent or received
uint8 SENT=0
uint8 RECEIVED=1
uint8 direction         # SENT: to the controller; RECEIVED: from it
string line             # the line, without its terminator (ASCII)
"""

WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
POINT_FIELD = "sensor_msgs/msg/PointField"
IMAGE = "sensor_msgs/msg/Image"
STRING = "std_msgs/msg/String"


def require_rosbags() -> None:
    """Raise the one-line :class:`LabrigError` when rosbags is not installed."""
    try:
        import rosbags  # noqa: F401
    except ImportError:
        raise LabrigError(f"ROS 2 bags need the rosbags package: {INSTALL_HINT}") from None


@cache
def typestore() -> Any:
    """rosbags' ROS 2 Humble type store (``tf2_msgs`` included) with EventPacket and labrig's own messages
    registered (built once)."""
    require_rosbags()
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for text, name in ((EVENT_PACKET_MSG, EVENT_PACKET), (PHASE_MSG, PHASE), (TRIGGER_EDGE_MSG, TRIGGER_EDGE),
                       (CNC_STATUS_MSG, CNC_STATUS), (GCODE_LINE_MSG, GCODE_LINE)):
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store
