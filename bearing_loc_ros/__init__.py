"""bearing_loc_ros: networked multi-station direction finding for ROS 2.

``bearing_loc_ros.core`` holds all numerics (numpy/scipy, never rclpy); the node modules and
``bearing_loc_ros.ros_conversions`` are the thin ROS layer; ``bearing_loc_ros.cli`` is the
``bearing_loc`` command line tool.
"""
