"""rosbag2 MCAP bags without ROS: the nuScenes topic layout, message building, writing a
scene and reading a bag back (rosbags and mcap only; never rclpy)."""
