"""ROS 2 over Zenoh the way rmw_zenoh carries it (``--zenoh-encoding rmw_zenoh``): wire.py is
the format (pure functions), sink.py the publishing node. docs/ros2.md."""
