"""The topics and frames labrig writes in a ROS 2 bag (docs/ros2.md has the table).

The camera topic is the Metavision driver's default (``/event_camera/events``); the rest name what
they carry. Frames: ``event_camera`` (sensor pixels), ``ft_sensor`` (the F/T sensor's own axes: its
reading is the force on the indenter), ``cnc_machine`` (the CNC's machine axes; the tool reference
point's position), ``gel`` (labrig's gel frame: origin at the centre of the undeformed top surface,
x along the marker columns, y along the rows, z out of the gel).
"""

from __future__ import annotations

EVENTS = "/event_camera/events"
WRENCH = "/ft_sensor/wrench"
POSE = "/cnc/pose"
CNC_STATUS = "/cnc/status"
GCODE = "/cnc/gcode"
PHASES = "/labrig/phases"
TRIGGER_OUT = "/labrig/trigger_out"
RECORDING = "/labrig/recording"

# a pipeline result (labrig run --out) and the live view
FORCE_FIELD = "/labrig/force_field"
NET_FORCE = "/labrig/net_force"
DEPTH = "/labrig/depth"
TRACKS = "/labrig/tracks"

CAMERA_FRAME = "event_camera"
FT_FRAME = "ft_sensor"
CNC_FRAME = "cnc_machine"
GEL_FRAME = "gel"
