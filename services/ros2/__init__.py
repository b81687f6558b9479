"""ROS 2 over Zenoh, without a ROS install: live topics into an agent (live.py), the fleet map
out as nav_msgs/OccupancyGrid and per-robot nav_msgs/Path (map_out.py), in rmw_zenoh's or
zenoh-bridge-ros2dds's key layout (names.py), CDR by rosbags (wire.py)."""
