"""occvo as a ROS 2 node over Zenoh, with no bridge: rmw_zenoh's key expressions, CDR payloads, attachments and
liveliness tokens (docs/ros2.md). Needs the `ros` extra (rosbags: message definitions and CDR)."""
