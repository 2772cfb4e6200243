"""The node's output messages, built from the plain field values of online/packing.py.

Nothing here decides anything: packing.py computes the values (ROS-free, unit-tested), this
module puts them into sensor_msgs / nav_msgs / visualization_msgs / diagnostic_msgs /
odg_ros_msgs messages. Large arrays are copied in as bytes (one memcpy), never as lists.
"""
from __future__ import annotations

import array

import numpy as np
from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, Quaternion, Vector3
from nav_msgs.msg import OccupancyGrid
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Float32, Float64, Header
from visualization_msgs.msg import Marker, MarkerArray

from odg_ros_msgs.msg import DynamicObject, DynamicObjectArray, SemanticVoxelGrid

from ..bev import bev_fields
from ..online import packing

OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)


def u8(data) -> array.array:
    """A uint8[] field value from bytes or a uint8 array (one memcpy)."""
    out = array.array("B")
    out.frombytes(data)
    return out


def refilled_u8(field: array.array, values: np.ndarray) -> array.array:
    """``field`` holding ``values`` (flat uint8): overwritten in place when the size is the
    same, so a grid a set costs one memcpy and no allocation."""
    if len(field) != values.size:
        return u8(values)
    np.frombuffer(field, np.uint8)[:] = values
    return field


def pose_msg(position, orientation_wxyz=(1.0, 0.0, 0.0, 0.0)) -> Pose:
    w, x, y, z = orientation_wxyz
    return Pose(position=Point(x=float(position[0]), y=float(position[1]),
                               z=float(position[2])),
                orientation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)))


class ReusedMessages:
    """The grid and object messages, refilled for each result instead of built anew: rclpy
    serialises a message inside publish(), so it is free again once publish returns, and
    building ~250 nested message objects a set (30 boxes) cost more than the rest of publish."""

    def __init__(self):
        self.grid = SemanticVoxelGrid()
        self.objects: list[DynamicObject] = []

    def grid_message(self, header: Header, fields: dict) -> SemanticVoxelGrid:
        grid = self.grid
        grid.header = header
        grid.origin = pose_msg(fields["origin_position"])
        grid.resolution = fields["resolution"]
        grid.size_x, grid.size_y, grid.size_z = \
            fields["size_x"], fields["size_y"], fields["size_z"]
        grid.memory_order = fields["memory_order"]
        grid.free_label, grid.unknown_label = fields["free_label"], fields["unknown_label"]
        grid.class_names = fields["class_names"]
        grid.labels = refilled_u8(grid.labels, fields["labels"])
        grid.confidence = refilled_u8(grid.confidence, fields["confidence"])
        grid.observed = refilled_u8(grid.observed, fields["observed"])
        return grid

    def object_array(self, header: Header, boxes: list[dict]) -> DynamicObjectArray:
        while len(self.objects) < len(boxes):
            self.objects.append(DynamicObject())
        for box, obj in zip(boxes, self.objects):
            o = packing.object_fields(box)
            obj.class_id, obj.class_name, obj.score = o["class_id"], o["class_name"], o["score"]
            position, orientation = obj.pose.position, obj.pose.orientation
            position.x, position.y, position.z = o["position"]
            orientation.w, orientation.x, orientation.y, orientation.z = o["orientation"]
            obj.size.x, obj.size.y, obj.size.z = o["size"]
            linear = obj.velocity.linear
            linear.x, linear.y, linear.z = o["velocity"]
        return DynamicObjectArray(header=header, objects=self.objects[:len(boxes)])


def cloud_message(header: Header, c: dict) -> PointCloud2:
    """PointCloud2 from packing.cloud_fields."""
    cloud = PointCloud2(header=header, height=c["height"], width=c["width"],
                        fields=[PointField(name=n, offset=o, datatype=d, count=k)
                                for n, o, d, k in c["fields"]],
                        is_bigendian=c["is_bigendian"], point_step=c["point_step"],
                        row_step=c["row_step"], is_dense=c["is_dense"])
    cloud.data = u8(c["data"])
    return cloud


def bev_message(header: Header, b: dict) -> OccupancyGrid:
    """OccupancyGrid from bev.bev_fields."""
    bev = OccupancyGrid(header=header)
    bev.info.map_load_time = header.stamp
    bev.info.resolution = b["resolution"]
    bev.info.width, bev.info.height = b["width"], b["height"]
    bev.info.origin = pose_msg(b["origin_position"])
    bev.data = array.array("b", b["data"])
    return bev


def marker_array(header: Header, objects: DynamicObjectArray) -> MarkerArray:
    """A translucent cube and a 'class score' label per object, after a DELETEALL."""
    markers = MarkerArray(markers=[Marker(header=header, action=Marker.DELETEALL)])
    for i, obj in enumerate(objects.objects):
        r, g, b = packing.box_color(obj.class_id)
        markers.markers.append(Marker(
            header=header, ns="objects", id=i, type=Marker.CUBE, action=Marker.ADD,
            pose=obj.pose, scale=Vector3(x=obj.size.x, y=obj.size.y, z=obj.size.z),
            color=ColorRGBA(r=r, g=g, b=b, a=0.5)))
        markers.markers.append(Marker(
            header=header, ns="labels", id=i, type=Marker.TEXT_VIEW_FACING,
            action=Marker.ADD, pose=pose_msg((obj.pose.position.x, obj.pose.position.y,
                                              obj.pose.position.z + obj.size.z)),
            scale=Vector3(z=0.8), color=ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0),
            text=f"{obj.class_name} {obj.score:.2f}"))
    return markers


def diagnostic_array(stamp, name: str, hardware_id: str, status: dict) -> DiagnosticArray:
    """One DiagnosticStatus from a PipelineStats.status dict."""
    message = DiagnosticStatus(
        level=bytes([status["level"]]), name=name, message=status["message"],
        hardware_id=hardware_id, values=[KeyValue(key=k, value=v) for k, v in status["values"]])
    return DiagnosticArray(header=Header(stamp=stamp), status=[message])



class Outputs:
    """The node's publishers and what goes out on them for one result: the grid and the
    objects always, the cloud, BEV and markers only to subscribers (building them costs)."""

    def __init__(self, node, cfg, frame: str, bev_band: tuple[float, float]):
        self.cfg, self.frame, self.bev_band = cfg, frame, bev_band
        self.reused = ReusedMessages()
        create = node.create_publisher
        self.grid = create(SemanticVoxelGrid, "~/occupancy", OUTPUT_QOS)
        self.cloud = create(PointCloud2, "~/occupancy/cloud", OUTPUT_QOS)
        self.bev = create(OccupancyGrid, "~/occupancy/bev", OUTPUT_QOS)
        self.objects = create(DynamicObjectArray, "~/objects", OUTPUT_QOS)
        self.markers = create(MarkerArray, "~/objects/markers", OUTPUT_QOS)
        self.fps = create(Float32, "~/fps", OUTPUT_QOS)
        self.processing_ms = create(Float64, "~/debug/processing_time_ms", OUTPUT_QOS)
        self.latency_ms = create(Float64, "~/debug/pipeline_latency_ms", OUTPUT_QOS)
        self.diagnostics = create(DiagnosticArray, "/diagnostics", 10)

    def publish(self, result) -> None:
        """One OnlineResult, stamped with its reference image's header stamp."""
        header = Header(stamp=result.header if isinstance(result.header, TimeMsg)
                        else TimeMsg(), frame_id=self.frame)
        cfg, observed = self.cfg, result.observed
        self.grid.publish(self.reused.grid_message(header, packing.voxel_grid_fields(
            result.grid, result.confidence, cfg.pc_range, cfg.voxel_size, cfg.labels,
            observed)))
        if self.cloud.get_subscription_count():
            self.cloud.publish(cloud_message(header, packing.cloud_fields(
                result.grid, cfg.pc_range, cfg.voxel_size, cfg.labels, observed)))
        if self.bev.get_subscription_count():
            self.bev.publish(bev_message(header, bev_fields(
                result.grid, cfg.pc_range, cfg.voxel_size, *self.bev_band, cfg.labels,
                observed)))
        objects = self.reused.object_array(header, result.boxes)
        self.objects.publish(objects)
        if self.markers.get_subscription_count():
            self.markers.publish(marker_array(header, objects))

    def publish_timing(self, processing_s: float, latency_s: float) -> None:
        """Autoware's debug topics, milliseconds: processing (steady clock) and pipeline
        latency (node clock)."""
        self.processing_ms.publish(Float64(data=processing_s * 1e3))
        self.latency_ms.publish(Float64(data=latency_s * 1e3))
