"""ROS 2 backend: the flight on ROS 2's own topics and types, with no bridge.

:mod:`backends.ros2.types` (the ROS types and their REP-2011 hashes), :mod:`backends.ros2.cdr`
(their plain CDR encoders) and :mod:`backends.ros2.topics` (gateway messages → ROS samples)
are shared by every way the samples leave: DDS (:mod:`backends.ros2.backend`, Cyclone DDS),
rmw_zenoh (through the ``zenoh`` backend's session) and the rosbag2 export.  The first three
need only the standard library.  See README.md in this directory.
"""
