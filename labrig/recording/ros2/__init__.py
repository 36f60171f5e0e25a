"""labrig recordings as ROS 2 bags and back, without a ROS installation.

``rosbags`` (pure Python; reads and writes ROS 2 bags in MCAP or sqlite3 storage, with its own CDR
type system) does the bag I/O; it is an optional dependency (``pip install 'labrig[ros2]'``), imported
only where a bag is read or written. The modules keep one idea each:

* :mod:`~labrig.recording.ros2.messages`: the message definitions (``.msg`` texts, registered with
  rosbags' type store) and the missing-package line;
* :mod:`~labrig.recording.ros2.topics`: the topic names and frames labrig writes;
* :mod:`~labrig.recording.ros2.event_packets`: camera events as ``event_camera_msgs/msg/EventPacket``
  payloads (EVT 3.0 from labrig's encoder; ``evt3``, ``mono`` and ``trigger`` decoded), sans-I/O;
* :mod:`~labrig.recording.ros2.mapping`: recording rows to messages and back, sans-I/O;
* :mod:`~labrig.recording.ros2.bag_export` and :mod:`~labrig.recording.ros2.bag_import`: the files.
"""
