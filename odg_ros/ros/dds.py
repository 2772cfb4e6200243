"""Keep DDS traffic on this machine.

Default Fast DDS discovery multicasts on every network interface. Every process that starts
rclpy for tests, demos and CI must first call :func:`use_localhost_dds` (or start its children
with the environment from :func:`localhost_dds_env`). The Fast DDS profile
``config/fastdds_localhost.xml`` then decides everything: shared memory plus UDPv4 bound to
127.0.0.1, unicast discovery to 127.0.0.1 only, no multicast.

Why ``ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT`` and not ``LOCALHOST``: with LOCALHOST,
rmw_fastrtps (Jazzy and later) appends its own SHM and *unrestricted* UDPv4 transports to the
profile's, and that UDPv4 transport binds sockets on every interface (measured here: one on
0.0.0.0 and one on the external address per process, and every datagram sent twice).
SYSTEM_DEFAULT is the value with which rmw_fastrtps leaves the profile's transports and
discovery settings as they are. Releases before Jazzy ignore the variable; the profile still
applies. This module does not import rclpy, so it can run before ``rclpy.init``.
"""
from __future__ import annotations

import os
from collections.abc import Mapping

from ..resources import resource_path

PROFILE_RELATIVE_PATH = "config/fastdds_localhost.xml"


def localhost_dds_env(env: Mapping[str, str] | None = None) -> dict[str, str]:
    """A copy of ``env`` (default ``os.environ``) set up for loopback-only DDS.

    Sets ``FASTDDS_DEFAULT_PROFILES_FILE`` (absolute path of the shipped profile),
    ``ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT`` (see the module docstring),
    ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp`` (the profile is a Fast DDS file; another RMW would
    ignore it) and drops ``ROS_LOCALHOST_ONLY`` (deprecated; it would override the range).
    Other variables, e.g. ``ROS_DOMAIN_ID``, are kept.
    """
    result = dict(os.environ if env is None else env)
    result["FASTDDS_DEFAULT_PROFILES_FILE"] = str(resource_path(PROFILE_RELATIVE_PATH).resolve())
    result["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SYSTEM_DEFAULT"
    result["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    result.pop("ROS_LOCALHOST_ONLY", None)
    return result


def use_localhost_dds() -> dict[str, str]:
    """Apply :func:`localhost_dds_env` to ``os.environ``; returns the variables it set.

    Must run before ``rclpy.init()`` in this process (the RMW reads them when the first
    participant is created); child processes inherit them.
    """
    env = localhost_dds_env()
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    changed = {key: value for key, value in env.items() if os.environ.get(key) != value}
    os.environ.update(changed)
    return changed
