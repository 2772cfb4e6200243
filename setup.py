"""Builds with pip (plain virtualenv) and with colcon (ament_python) on a ROS 2 install."""
import os
from glob import glob

from setuptools import find_packages, setup

package_name = "odg_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=["odg_ros", "odg_ros.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml", "LICENSE"]),
        ("share/" + package_name + "/launch", glob("launch/*.py")),
        ("share/" + package_name + "/config",
         [p for p in glob("config/*") if os.path.isfile(p)]),
        ("share/" + package_name + "/config/bags", glob("config/bags/*.yaml")),
        ("share/" + package_name + "/model", glob("model/*.yaml") + glob("model/*.md")
         + glob("model/*.pt")),
        ("share/" + package_name + "/model/int8", glob("model/int8/*.json")),
    ],
    install_requires=["numpy", "scipy", "pyyaml", "tqdm", "pillow", "matplotlib"],
    zip_safe=True,
    maintainer="odg_ros developers",
    maintainer_email="odg-ros-dev@example.com",
    description="ODG occupancy prediction with dual Gaussian queries as a ROS 2 node",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "odg = odg_ros.commands:main",
            "odg_node = odg_ros.ros.node:main",
        ],
    },
)
