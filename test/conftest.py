"""Suite-wide settings: torch on the machine's 2 cores and deterministic; loopback-only DDS for
this process and every child it starts, a ROS domain of its own per test session, and rclpy
fixtures that skip (with the reason) when rclpy cannot be imported. Tests that need no rclpy
(bag writing and reading, the node's ROS-free core) run regardless."""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see odg_ros/__init__.py

import pytest  # noqa: E402
import torch  # noqa: E402

from odg_ros.ros.dds import use_localhost_dds  # noqa: E402

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


# Before any rclpy.init in this process; children inherit os.environ.
use_localhost_dds()
# Parallel test sessions on one machine must not hear each other: a domain per session
# (0..101 are the domains every RMW supports; 0 is the usual default, keep clear of it).
os.environ["ROS_DOMAIN_ID"] = str(1 + os.getpid() % 100)

try:
    import rclpy  # noqa: F401
    RCLPY_ERROR = None
except Exception as error:  # ImportError, or a missing shared library of the ROS wheels
    RCLPY_ERROR = f"{type(error).__name__}: {error}"


@pytest.fixture
def rclpy_module():
    """rclpy, or skip: the ROS 2 Python wheels (make setup) are not usable here."""
    if RCLPY_ERROR is not None:
        pytest.skip(f"rclpy is not importable ({RCLPY_ERROR}); run `make setup`")
    import rclpy
    return rclpy


@pytest.fixture
def ros_context(rclpy_module):
    """A fresh rclpy context for one test, shut down afterwards."""
    context = rclpy_module.Context()
    rclpy_module.init(context=context)
    yield context
    context.try_shutdown()


@pytest.fixture(scope="session")
def layout_world(tmp_path_factory):
    """One synthetic scene (keyframe gaps 0.55 and 0.75 s) as a bag of every nuScenes
    converter layout (testing/bag_layouts.py): shared by the bag and the node tests."""
    from testing.bag_layouts import build_layout_world
    return build_layout_world(tmp_path_factory.mktemp("layout_world"))
