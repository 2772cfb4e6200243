"""odg_ros: ODG (Occupancy prediction using Dual Gaussians) as a ROS 2 perception node.

Importing this package (or anything under ``odg_ros.network``, ``odg_ros.data``,
``odg_ros.metrics``, ``odg_ros.online``) never imports rclpy; only ``odg_ros.ros`` does.
"""

__version__ = "0.1.0"
