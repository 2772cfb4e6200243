"""Occupancy metrics: voxel mIoU + geometry IoU (``miou``), RayIoU and its
LiDAR origins (``rayiou``, ray casting in ``raycast``), split scoring and reports (``score``)."""
from .miou import MIoU
from .rayiou import LidarOrigins, RayIoU, lidar_origins
from .raycast import cast_rays, lidar_ray_directions
from .score import OccScore, format_table

__all__ = ["MIoU", "RayIoU", "LidarOrigins", "lidar_origins", "cast_rays",
           "lidar_ray_directions", "OccScore", "format_table"]
