"""The node's own work per camera set, stage by stage: everything but the model.

Six 1600x900 JPEGs per set (nuScenes' cameras, the shipped rig's intrinsics and
extrinsics, odometry poses at 50 Hz) go through the node's real code: ``on_image`` and the
camera-set sync, the lookup of camera infos, poses and extrinsics, JPEG decoding with
resize/crop, the predictor's host side (history, packed geometry, image copy; results back
and into box dicts) and the node's ``publish`` (packing and message construction, real
rclpy publishers with every optional output on). The model is one real step of the preset
(random weights, or --checkpoint) run once; its outputs are then replayed, so the stages
see a real grid and real boxes and the model's time is left out.

    python tools/measure_node_overhead.py                       # odg_cpu and odg_t, 30 sets
    python tools/measure_node_overhead.py --preset odg_t --sets 50 --images 'cams/*.jpg'

The images are synthetic (textured, ~nuScenes' JPEG size) unless --images names six or
more JPEGs of one size. Prints the median per stage in ms and the total without decoding.
"""
from __future__ import annotations

import argparse
import glob
import io
import os
import statistics
import sys
import time
import types

import numpy as np
from PIL import Image

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from odg_ros.geometry import make_transform                          # noqa: E402
from odg_ros.online.images import EncodedImage                       # noqa: E402
from odg_ros.online.pipeline import OnlinePipeline, PipelineSettings  # noqa: E402
from odg_ros.online.predictor import OnlinePredictor                 # noqa: E402
from odg_ros.online.rig import load_rig                              # noqa: E402
from odg_ros.resources import resource_path                          # noqa: E402

RIG = load_rig(resource_path("config/rig_nuscenes.yaml"))
CAMS = tuple(RIG.cameras)
OFFSETS = (0.0, 0.008, 0.017, 0.025, 0.033, 0.042)     # nuScenes' firing order, s
# "sync" (on_image of six cameras and the set sync) and "ego2img" are timed here; the rest
# are the stages the node reports in its diagnostics.
STAGES = ("sync", "lookup", "decode_images", "upload", "download", "publish")


def synthetic_jpegs(count: int, hw=(900, 1600), quality: int = 90, seed: int = 0) -> list:
    """Textured images (smooth shading, edges, fine noise) whose JPEGs are about the size of
    nuScenes' camera JPEGs (~150-250 kB at 1600x900)."""
    rng = np.random.default_rng(seed)
    h, w = hw
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    out = []
    for _ in range(count):
        image = np.zeros((h, w, 3), np.float32)
        for c in range(3):
            for _ in range(6):
                fx, fy = rng.uniform(0.002, 0.05, 2)
                image[..., c] += 20 * np.sin(fx * x + fy * y + rng.uniform(0, 6.3))
        for _ in range(40):                                       # boxes: hard edges
            y0, x0 = rng.integers(0, h - 50), rng.integers(0, w - 50)
            image[y0:y0 + rng.integers(20, 200), x0:x0 + rng.integers(20, 300)] += \
                rng.uniform(-60, 60, 3)
        image += rng.normal(0, 4, image.shape)
        pixels = np.clip(image + 128, 0, 255).astype(np.uint8)
        buffer = io.BytesIO()
        Image.fromarray(pixels).save(buffer, format="JPEG", quality=quality)
        out.append(buffer.getvalue())
    return out


def file_jpegs(pattern: str) -> list:
    paths = sorted(glob.glob(pattern))
    if len(paths) < len(CAMS):
        raise SystemExit(f"--images {pattern!r}: {len(paths)} files, need {len(CAMS)}")
    data = [open(p, "rb").read() for p in paths[:len(CAMS)]]
    sizes = {Image.open(io.BytesIO(d)).size for d in data}
    if len(sizes) != 1:
        raise SystemExit(f"--images: the JPEGs differ in size {sizes}")
    return data


def pose_at(t: float) -> np.ndarray:
    yaw = 0.02 * t
    return make_transform([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)], (5.0 * t, 0.1 * t, 0.0))


def ros_publisher_self(cfg, stats):
    """A stand-in ``self`` for OdgNode.publish with real rclpy publishers, every optional
    output on (as if subscribed); None where rclpy is not importable."""
    try:
        import rclpy
        from odg_ros.ros import node as node_module
        from odg_ros.ros.dds import use_localhost_dds
    except ImportError as error:
        print(f"rclpy not importable ({error}): publish times packing only")
        return None, None
    use_localhost_dds()
    rclpy.init()
    ros_node = rclpy.create_node("measure_node_overhead")
    m = node_module

    def publisher(msg_type, topic):
        real = ros_node.create_publisher(msg_type, topic, m.OUTPUT_QOS)
        return types.SimpleNamespace(publish=real.publish, get_subscription_count=lambda: 1)

    fake = types.SimpleNamespace(
        cfg=cfg, output_frame="base_link", stats=stats, now_seconds=time.time,
        params={"bev_min_z": 0.0, "bev_max_z": 2.0},
        pub_grid=publisher(m.SemanticVoxelGrid, "occupancy"),
        pub_cloud=publisher(m.PointCloud2, "occupancy/cloud"),
        pub_bev=publisher(m.OccupancyGrid, "occupancy/bev"),
        pub_objects=publisher(m.DynamicObjectArray, "objects"),
        pub_markers=publisher(m.MarkerArray, "objects/markers"))
    return (lambda result: m.OdgNode.publish(fake, result)), (ros_node, rclpy)


def packing_only(cfg):
    from odg_ros.online import packing

    def publish(result):
        packing.voxel_grid_fields(result.grid, result.confidence, cfg.pc_range,
                                  cfg.voxel_size, cfg.labels)
        packing.cloud_fields(result.grid, cfg.pc_range, cfg.voxel_size, cfg.labels)
        packing.bev_fields(result.grid, cfg.pc_range, cfg.voxel_size, 0.0, 2.0, cfg.labels)
        for box in result.boxes:
            packing.object_fields(box)
    return publish


def measure(preset: str, jpegs: list, sets: int, checkpoint: str | None, publish_with) -> dict:
    from odg_ros.network.checkpoint import load_model
    model, cfg = load_model(checkpoint, preset=preset)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, compile="eager")
    height, width = Image.open(io.BytesIO(jpegs[0])).size[::-1]
    settings = PipelineSettings(CAMS)
    pipeline = OnlinePipeline(predictor, settings,
                              lambda camera, frame_id, stamp: RIG.cameras[camera].sensor2ego)
    scale = np.diag([width / 1600, height / 900, 1.0])
    for name in CAMS:
        pipeline.on_camera_info(name, scale @ RIG.cameras[name].intrinsics, height, width,
                                frame_id=name)
    t_end = 10.0 + (sets + 3) / 12
    for t in np.arange(9.5, t_end + 0.5, 0.02):                 # 50 Hz odometry
        pipeline.on_pose(float(t), pose_at(float(t)))

    def feed(start):
        for name, offset, data in zip(CAMS, OFFSETS, jpegs):
            pipeline.on_image(name, start + offset, EncodedImage(True, "jpeg", data), now=0.0,
                              header=None)

    # one real model step, then its outputs replayed
    feed(10.0)
    t0 = time.perf_counter()
    pipeline.process(pipeline.next_set(timeout=1.0))
    model_ms = (time.perf_counter() - t0) * 1e3
    recorded = tuple(o.clone() for o in predictor._run())
    predictor._run = lambda: recorded

    from odg_ros.online.diagnostics import PipelineStats
    publish = publish_with(cfg, PipelineStats()) if publish_with else packing_only(cfg)
    times = {stage: [] for stage in STAGES}
    result = None
    for k in range(1, sets + 1):
        start = 10.0 + k / 12
        t0 = time.perf_counter()
        feed(start)
        camera_set = pipeline.next_set(timeout=1.0)
        t1 = time.perf_counter()
        result = pipeline.process(camera_set)
        t2 = time.perf_counter()
        publish(result)
        t3 = time.perf_counter()
        times["sync"].append(t1 - t0)
        times["publish"].append(t3 - t2)
        for stage in ("lookup", "decode_images", "upload", "download"):
            times[stage].append(result.timings[stage])
        times.setdefault("model (replayed)", []).append(result.timings["model"])
    pipeline.close()
    medians = {stage: statistics.median(v) * 1e3 for stage, v in times.items()}
    medians["total without decoding"] = sum(medians[s] for s in STAGES
                                            if s != "decode_images")
    return {"preset": preset, "input": cfg.image_size, "sets": sets,
            "jpeg_kb": round(statistics.mean(len(d) for d in jpegs) / 1024),
            "jpeg_hw": (height, width), "model_ms_one_step": model_ms,
            "occupied_voxels": int((result.grid != cfg.labels.free_label).sum()),
            "boxes": len(result.boxes), "median_ms": medians}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="odg_cpu,odg_t",
                        help="comma-separated presets (default: odg_cpu,odg_t)")
    parser.add_argument("--sets", type=int, default=30, help="camera sets timed (median)")
    parser.add_argument("--checkpoint", default=None, help="weights (default: random)")
    parser.add_argument("--images", default=None,
                        help="glob of six JPEGs of one size (default: synthetic 1600x900)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--no-ros", action="store_true",
                        help="publish: packing only, no rclpy messages")
    args = parser.parse_args(argv)
    if args.threads:
        import torch
        torch.set_num_threads(args.threads)
    jpegs = file_jpegs(args.images) if args.images else synthetic_jpegs(len(CAMS))
    ros = None
    publish_with = None
    if not args.no_ros:
        def publish_with(cfg, stats):
            nonlocal ros
            publish, ros = ros_publisher_self(cfg, stats)
            return publish
    try:
        for preset in args.preset.split(","):
            r = measure(preset.strip(), jpegs, args.sets, args.checkpoint, publish_with)
            if ros is not None:
                ros[0].destroy_node()
                ros[1].shutdown()
                ros = None
            print(f"{r['preset']}: input {r['input'][0]}x{r['input'][1]}, six "
                  f"{r['jpeg_hw'][0]}x{r['jpeg_hw'][1]} JPEGs (~{r['jpeg_kb']} kB each), "
                  f"{r['occupied_voxels']} occupied voxels, {r['boxes']} boxes; one model "
                  f"step {r['model_ms_one_step']:.0f} ms (not included); median of "
                  f"{r['sets']} sets:")
            for stage, ms in r["median_ms"].items():
                print(f"  {stage:<24}{ms:8.2f} ms")
    finally:
        if ros is not None:
            ros[0].destroy_node()
            ros[1].shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
