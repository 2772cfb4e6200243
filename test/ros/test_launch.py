"""launch/odg.launch.py: the node action gets the params file, use_sim_time, the namespace and
a remapping of every input topic. Needs launch_ros (a ROS 2 install; no PyPI wheel)."""
import importlib.util

import pytest

from odg_ros.resources import resource_path

launch_ros = pytest.importorskip("launch_ros", reason="launch_ros is only on a ROS 2 install")
import launch  # noqa: E402  (comes with launch_ros)

CAMS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT",
        "CAM_BACK_RIGHT")


def load_launch_module():
    spec = importlib.util.spec_from_file_location("odg_launch",
                                                  resource_path("launch/odg.launch.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def expanded(node, name):
    """launch_ros exposes expanded values as properties on recent releases."""
    if hasattr(node, name):
        return getattr(node, name)
    private = name.replace("expanded_remapping_rules", "expanded_remappings")
    return getattr(node, f"_Node__{private}")


def test_launch_description_node_parameters_and_remappings():
    description = load_launch_module().generate_launch_description()
    context = launch.LaunchContext()
    context.launch_configurations.update({"namespace": "car1", "use_sim_time": "true",
                                          "CAM_FRONT_image": "/front/jpeg", "odom": "/ego/odom"})
    nodes = []
    for entity in description.entities:
        if isinstance(entity, launch.actions.DeclareLaunchArgument):
            entity.visit(context)                      # defaults for the others
        elif isinstance(entity, launch_ros.actions.Node):
            nodes.append(entity)
    assert len(nodes) == 1
    node = nodes[0]
    node._perform_substitutions(context)
    assert expanded(node, "expanded_node_namespace") == "/car1"
    remaps = dict(expanded(node, "expanded_remapping_rules"))
    assert len(remaps) == 2 * len(CAMS) + 3
    assert remaps["/CAM_FRONT/image_rect_compressed"] == "/front/jpeg"
    assert remaps["/CAM_BACK/camera_info"] == "/CAM_BACK/camera_info"
    assert remaps["/odom"] == "/ego/odom" and remaps["/tf"] == "/tf"
    from launch_ros.utilities import evaluate_parameters
    params = evaluate_parameters(context, node._Node__parameters)
    assert [str(p) for p in params if not isinstance(p, dict)] == \
        [str(resource_path("config/odg.yaml"))]
    assert [p for p in params if isinstance(p, dict)] == [{"use_sim_time": True}]
