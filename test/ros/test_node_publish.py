"""The node's Outputs (ros/output_messages.py) refill the same grid and object messages for every
result: what they publish must equal, after serialisation, the messages built anew, field by
field, for each result, whatever the results before them (more boxes, another grid).
(Compared as deserialised messages: the serialised bytes hold uninitialised CDR padding.)"""
from __future__ import annotations

import types

import numpy as np

from odg_ros.classes import BOX_CLASSES, LABEL_SETS
from odg_ros.online import packing

LABELS = LABEL_SETS["nuscenes"]
PC_RANGE = (-2.0, -1.6, -1.0, 2.0, 1.6, 0.6)
GRID = (10, 8, 4)


def result(seed: int, boxes: int):
    from builtin_interfaces.msg import Time
    rng = np.random.default_rng(seed)
    grid = rng.integers(0, LABELS.free_label + 1, GRID).astype(np.uint8)
    confidence = rng.integers(0, 256, GRID).astype(np.uint8)
    box_list = [{"label": int(label), "class_name": BOX_CLASSES[int(label)],
                 "score": float(rng.uniform()), "center": rng.normal(size=3).tolist(),
                 "size": rng.uniform(0.5, 5, 3).tolist(), "yaw": float(rng.uniform(-3, 3)),
                 "velocity": rng.normal(size=2).tolist()}
                for label in rng.integers(0, len(BOX_CLASSES), boxes)]
    observed = rng.integers(0, 2, GRID).astype(bool)
    return types.SimpleNamespace(header=Time(sec=100 + seed, nanosec=seed), stamp=100.0 + seed,
                                 grid=grid, confidence=confidence, boxes=box_list, timings={},
                                 observed=observed)


def built_anew(res, frame: str):
    """The grid and object messages constructed from nothing, field by field."""
    from geometry_msgs.msg import Point, Pose, Quaternion, Vector3
    from odg_ros_msgs.msg import DynamicObject, DynamicObjectArray, SemanticVoxelGrid
    from std_msgs.msg import Header
    header = Header(stamp=res.header, frame_id=frame)
    X, Y, Z = GRID
    grid = SemanticVoxelGrid(
        header=header, origin=Pose(position=Point(x=PC_RANGE[0], y=PC_RANGE[1], z=PC_RANGE[2])),
        resolution=0.4, size_x=X, size_y=Y, size_z=Z, memory_order="xyz_c",
        free_label=LABELS.free_label, unknown_label=255, class_names=list(LABELS.names),
        labels=res.grid.tobytes(), confidence=res.confidence.tobytes(),
        observed=res.observed.astype(np.uint8).tobytes())
    objects = DynamicObjectArray(header=header)
    for box in res.boxes:
        w, length, h = box["size"]
        yaw = box["yaw"]
        obj = DynamicObject(class_id=box["label"], class_name=box["class_name"],
                            score=box["score"],
                            pose=Pose(position=Point(x=box["center"][0], y=box["center"][1],
                                                     z=box["center"][2]),
                                      orientation=Quaternion(z=np.sin(yaw / 2),
                                                             w=np.cos(yaw / 2))),
                            size=Vector3(x=length, y=w, z=h))
        obj.velocity.linear = Vector3(x=box["velocity"][0], y=box["velocity"][1])
        objects.objects.append(obj)
    return grid, objects


def test_refilled_messages_are_sent_like_new_ones(rclpy_module):
    from rclpy.serialization import deserialize_message, serialize_message
    from odg_ros.ros import output_messages as messages_module

    def sent(msg):
        return deserialize_message(serialize_message(msg), type(msg))

    published = {}

    class Recorder:
        """Serialises at publish time, as rclpy does: a message refilled later must not
        change what was published."""

        def __init__(self, topic, subscribers=0):
            self.topic, self.subscribers = topic, subscribers

        def publish(self, msg):
            published.setdefault(self.topic, []).append(sent(msg))

        def get_subscription_count(self):
            return self.subscribers

    names = {"~/occupancy": "grid", "~/objects": "objects", "~/objects/markers": "markers"}

    def create_publisher(msg_type, topic, qos):
        return Recorder(names.get(topic, topic), subscribers=int(topic in names))

    outputs = messages_module.Outputs(
        types.SimpleNamespace(create_publisher=create_publisher),
        types.SimpleNamespace(pc_range=PC_RANGE, voxel_size=0.4, labels=LABELS),
        "base_link", (0.0, 2.0))
    # more boxes, then fewer, none, more again; a new grid each time
    results = [result(seed, boxes) for seed, boxes in enumerate((3, 1, 0, 5))]
    for res in results:
        outputs.publish(res)
    for i, res in enumerate(results):
        grid, objects = built_anew(res, "base_link")
        assert published["grid"][i] == sent(grid), f"grid of result {i}"
        assert published["objects"][i] == sent(objects), f"objects of result {i}"
    assert len(published["markers"]) == len(results)       # built from the refilled objects


def test_grid_fields_are_copied_once_into_the_reused_field(rclpy_module):
    import array
    from odg_ros.ros.output_messages import refilled_u8 as _refilled_u8
    field = array.array("B", bytes(6))
    values = np.arange(6, dtype=np.uint8)
    assert _refilled_u8(field, values) is field and field.tolist() == list(range(6))
    bigger = _refilled_u8(field, np.arange(9, dtype=np.uint8))  # another size: a new field
    assert bigger is not field and bigger.tolist() == list(range(9))
