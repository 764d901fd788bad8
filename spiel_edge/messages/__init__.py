"""ROS 2 messages as bytes: the message definitions (ros2_types), CDR encoding and decoding
(cdr), the records turned into sensor_msgs/tf2 messages (ros2_messages) with the sensor's
limits (ros2_limits), and the settings they take (settings: frame id, static transforms).

Below both ``recordings`` (a ros2 MCAP recording) and ``outputs`` (Zenoh, Foxglove), which
share it; it imports neither."""
