"""Start odg_node: ``ros2 launch odg_ros odg.launch.py``.

Arguments:
  params_file   node parameters (default: the installed config/odg.yaml)
  namespace     ROS namespace of the node (outputs are ~/..., so they move with it)
  use_sim_time  true when replaying a bag with --clock
  <input>       one remapping per input topic, e.g. CAM_FRONT_image:=/front/compressed,
                CAM_FRONT_camera_info:=..., odom:=..., tf:=..., tf_static:=...

The remappings rename the input topics as config/odg.yaml names them (camera names and the
image / camera_info / odometry topic patterns); with a params file that changes those names,
remap its names instead (``--ros-args -r`` style) or edit the file.
"""
import yaml
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from odg_ros.resources import resource_path


def input_topics(params_path) -> list[tuple[str, str]]:
    """(launch argument, topic) for every input the node subscribes with these parameters."""
    with open(params_path) as f:
        params = yaml.safe_load(f)["/**"]["ros__parameters"]
    topics = []
    for camera in params["camera_names"]:
        topics.append((f"{camera}_image", params["image_topic"].format(camera=camera)))
        topics.append((f"{camera}_camera_info",
                       params["camera_info_topic"].format(camera=camera)))
    topics += [("odom", params["odometry_topic"]), ("tf", "/tf"), ("tf_static", "/tf_static")]
    return topics


def generate_launch_description():
    default_params = str(resource_path("config/odg.yaml"))
    topics = input_topics(default_params)
    arguments = [
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="odg_node parameters (ROS params YAML)"),
        DeclareLaunchArgument("namespace", default_value="", description="node namespace"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="use /clock (bag replay)"),
    ] + [DeclareLaunchArgument(name, default_value=topic, description=f"remap {topic}")
         for name, topic in topics]
    node = Node(
        package="odg_ros", executable="odg_node", name="odg_node",
        namespace=LaunchConfiguration("namespace"), output="screen",
        parameters=[LaunchConfiguration("params_file"),
                    {"use_sim_time": ParameterValue(LaunchConfiguration("use_sim_time"),
                                                    value_type=bool)}],
        remappings=[(topic, LaunchConfiguration(name)) for name, topic in topics])
    return LaunchDescription(arguments + [node])
