"""The ROS 2 side of odg_ros: the only package allowed to import rclpy.

Modules: ``dds`` (loopback-only DDS set-up, import before rclpy.init), ``bag`` (rosbag2 MCAP
writer/reader, rclpy-free), ``replay`` (publish a bag with rclpy), ``node`` (the online node).
Importing this package imports nothing heavy; each module imports what it needs.
"""
