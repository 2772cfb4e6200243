"""The online pipeline, ROS-free: camera set sync, pose interpolation, TF buffer, camera
extrinsics (TF or rig file), sets waiting for their poses, image decoding, feature history,
latest-wins mailbox, streaming predictor, diagnostics, message packing. ``pipeline.OnlinePipeline`` ties them together; odg_ros/ros/node.py only converts
ROS messages to and from it. Nothing here imports rclpy."""
