"""Pure numpy/scipy core of bearing_loc_ros. Never imports rclpy or ROS message types."""
