"""The node's own work per camera set, stage by stage: everything but the model.

Six 1600x900 JPEGs per set (nuScenes' cameras, the shipped rig's intrinsics and
extrinsics, odometry poses at 50 Hz) go through the node's real code: ``on_image`` and the
camera-set sync, the look-up of camera infos, poses and extrinsics with ego2img, JPEG
decoding with resize/crop, the predictor's host side (history, packed geometry, image
copy; results back and into box dicts) and the node's ``publish`` (packing, message
construction, real rclpy publishers), once with the default outputs (grid and objects) and
once with the cloud, BEV and markers too (as if subscribed). The model is one real step of
the preset (random weights, or --checkpoint) run once; its outputs are then replayed with
``--occupied`` voxels and ``--boxes`` boxes, so the model's time is left out.

    python -m tools.measure_node_overhead                      # odg_cpu and odg_t, 30 sets
    python -m tools.measure_node_overhead --preset odg_t --images 'cams/*.jpg' --model-ms 40

Prints medians per stage: wall time, and the CPU time of the calling thread (which other
processes on a busy machine do not inflate). --model-ms also times sets per second with the
model as a sleep, decoding in the model's thread or ahead of it. The images are synthetic
(textured, ~nuScenes' JPEG size) unless --images names six or more JPEGs of one size.
"""
from __future__ import annotations

import argparse
import glob
import io
import os
import statistics
import time
import types

import numpy as np
from PIL import Image


from odg_ros.bev import bev_fields
from odg_ros.geometry import make_transform                        
from odg_ros.online.images import EncodedImage                     
from odg_ros.online.pipeline import OnlinePipeline, PipelineSettings
from odg_ros.online.predictor import OnlinePredictor               
from odg_ros.online.camera_calibration import load_rig                            
from odg_ros.resources import resource_path                        

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
    """The node's Outputs.publish (and its stats) with real rclpy publishers (no subscribers:
    serialised, not sent); ``optional``: the cloud, BEV and markers too, as if subscribed.
    None where rclpy is not importable."""
    try:
        import rclpy
        from odg_ros.ros import output_messages as messages_module
        from odg_ros.ros.dds import use_localhost_dds
    except ImportError as error:
        print(f"rclpy not importable ({error}): publish times packing only")
        return None, None
    use_localhost_dds()
    rclpy.init()
    ros_node = rclpy.create_node("measure_node_overhead")
    subscribed = {"optional": 1}
    required = ("occupancy", "objects")

    def create_publisher(msg_type, topic, qos):
        real = ros_node.create_publisher(msg_type, topic.removeprefix("~/"), qos)
        if topic.removeprefix("~/") in required:
            return real
        return types.SimpleNamespace(publish=real.publish,
                                     get_subscription_count=lambda: subscribed["optional"])

    outputs = messages_module.Outputs(types.SimpleNamespace(create_publisher=create_publisher),
                                      cfg, "base_link", (0.0, 2.0))

    def publish(result, optional: bool):
        subscribed["optional"] = int(optional)
        start = time.perf_counter()
        outputs.publish(result)
        stats.record_output(result.stamp, time.time(), {"publish": time.perf_counter() - start},
                            received=result.received)

    return publish, (ros_node, rclpy)


def packing_only(cfg):
    from odg_ros.online import packing

    def publish(result, optional: bool):
        packing.voxel_grid_fields(result.grid, result.confidence, cfg.pc_range,
                                  cfg.voxel_size, cfg.labels)
        for box in result.boxes:
            packing.object_fields(box)
        if optional:
            packing.cloud_fields(result.grid, cfg.pc_range, cfg.voxel_size, cfg.labels)
            bev_fields(result.grid, cfg.pc_range, cfg.voxel_size, 0.0, 2.0,
                               cfg.labels)
    return publish


def replayed_outputs(outputs, cfg, occupied: int, boxes: int):
    """The step's outputs (labels, confidence, boxes, score, label, valid, observed), with
    random voxels labelled until ``occupied`` are (random weights predict an empty grid) and
    the ``boxes`` best boxes valid: the publishing cost of a busy scene."""
    labels, confidence, box, score, label, valid, observed = (o.clone() for o in outputs)
    free = cfg.labels.free_label
    missing = occupied - int((labels != free).sum())
    if missing > 0:
        rng = np.random.default_rng(0)
        empty = np.flatnonzero(labels.numpy() == free)
        chosen = rng.choice(empty, size=min(missing, len(empty)), replace=False)
        labels.numpy()[chosen] = rng.integers(0, free, len(chosen))
    valid[:] = False
    valid[:boxes] = True
    return labels, confidence, box, score, label, valid, observed


def measure_overlap(pipeline, feed, start: float, model_ms: float, sets: int) -> dict:
    """Sets per second with the model standing in as a ``model_ms`` sleep (a GPU step
    leaves the CPU free), decoding in the worker (serial) or ahead of it (overlapped),
    rounds of 5 sets interleaved; a fresh set is always waiting (the source is never
    the bottleneck). -> median ms per set of each."""
    replay = pipeline.predictor._run
    pipeline.predictor._run = lambda images: (time.sleep(model_ms / 1e3), replay(images))[1]
    stamp = [start]

    def next_stamp():
        stamp[0] += 1 / 12
        return stamp[0]

    def serial():                     # the worker waits for each set's decoding
        feed(next_stamp())
        pipeline.infer(pipeline.next_prepared(timeout=5.0))

    def overlapped():
        prepared = pipeline.next_prepared(timeout=5.0)
        feed(next_stamp())            # decodes while the model runs on ``prepared``
        pipeline.infer(prepared)

    periods = {"serial": [], "overlapped": []}
    pipeline.start_decoding(lambda error: print(error), lambda: print("error"))
    for _ in range(max(1, sets // 5)):
        for name, one in (("serial", serial), ("overlapped", overlapped)):
            if name == "overlapped":
                feed(next_stamp())
            t0 = time.perf_counter()
            for _ in range(5):
                one()
            periods[name].append((time.perf_counter() - t0) / 5 * 1e3)
            if name == "overlapped":
                pipeline.next_prepared(timeout=5.0)     # the set decoded last
    pipeline.predictor._run = replay
    return {name: statistics.median(v) for name, v in periods.items()}


def measure(preset: str, jpegs: list, sets: int, checkpoint: str | None, publish_with,
            occupied: int = 40000, boxes: int = 30, model_ms: float = 0.0) -> dict:
    from odg_ros.network.checkpoint import load_model
    model, cfg = load_model(checkpoint, preset=preset)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, compile="eager")
    height, width = Image.open(io.BytesIO(jpegs[0])).size[::-1]
    settings = PipelineSettings.from_parameters(CAMS)
    pipeline = OnlinePipeline(predictor, settings,
                              lambda camera, frame_id, stamp: RIG.cameras[camera].sensor2ego)
    scale = np.diag([width / 1600, height / 900, 1.0])
    for name in CAMS:
        pipeline.on_camera_info(name, scale @ RIG.cameras[name].intrinsics, height, width,
                                frame_id=name)
    t_end = 10.0 + (3 * sets + 12) / 12           # the overlap rounds too
    for t in np.arange(9.5, t_end + 0.5, 0.02):                 # 50 Hz odometry
        pipeline.on_pose(float(t), pose_at(float(t)))

    def feed(start):
        for name, offset, data in zip(CAMS, OFFSETS, jpegs):
            pipeline.on_image(name, start + offset, EncodedImage(True, "jpeg", data), now=0.0,
                              header=None)

    # one real model step, then its outputs replayed
    real_run, stepped = predictor._run, []
    predictor._run = lambda images, budget: stepped.append(real_run(images, budget)) or \
        stepped[-1]
    feed(10.0)
    t0 = time.perf_counter()
    pipeline.process(pipeline.next_set(timeout=1.0))
    step_ms = (time.perf_counter() - t0) * 1e3
    recorded = replayed_outputs(stepped[0], cfg, occupied, boxes)
    predictor._run = lambda images, budget: recorded

    from odg_ros.online.diagnostics import PipelineStats
    publish = publish_with(cfg, PipelineStats()) if publish_with else packing_only(cfg)
    times = {stage: [] for stage in STAGES}
    # CPU seconds of the calling thread (time.thread_time): what other processes on a
    # busy machine do not inflate; decoding runs in a pool, so prepare's CPU time here is
    # its look-ups and ego2img
    cpu = {"sync": [], "prepare (without decoding)": [], "infer (upload, download)": [],
           "publish": [], "publish, all outputs": []}
    result = None
    for k in range(1, sets + 1):
        start = 10.0 + k / 12
        t0, c0 = time.perf_counter(), time.thread_time()
        feed(start)
        camera_set = pipeline.next_set(timeout=1.0)
        t1, c1 = time.perf_counter(), time.thread_time()
        prepared = pipeline.prepare(camera_set)
        c2 = time.thread_time()
        result = pipeline.infer(prepared)
        t3, c3 = time.perf_counter(), time.thread_time()
        publish(result, optional=False)
        t4, c4 = time.perf_counter(), time.thread_time()
        publish(result, optional=True)
        t5, c5 = time.perf_counter(), time.thread_time()
        times["sync"].append(t1 - t0)
        times["publish"].append(t4 - t3)
        times.setdefault("publish, all outputs", []).append(t5 - t4)
        for stage in ("lookup", "decode_images", "upload", "download"):
            times[stage].append(result.timings[stage])
        times.setdefault("model (replayed)", []).append(result.timings["model"])
        for name, seconds in zip(cpu, (c1 - c0, c2 - c1, c3 - c2, c4 - c3, c5 - c4)):
            cpu[name].append(seconds)
    overlap = measure_overlap(pipeline, feed, 10.0 + (sets + 1) / 12, model_ms, sets) \
        if model_ms else None
    pipeline.close()
    medians = {stage: statistics.median(v) * 1e3 for stage, v in times.items()}
    medians["total without decoding"] = sum(medians[s] for s in STAGES
                                            if s != "decode_images")
    medians["total, all outputs"] = (medians["total without decoding"] - medians["publish"]
                                     + medians["publish, all outputs"])
    cpu_medians = {name: statistics.median(v) * 1e3 for name, v in cpu.items()}
    cpu_medians["total without decoding"] = sum(cpu_medians.values()) \
        - cpu_medians["publish, all outputs"]
    cpu_medians["total, all outputs"] = (cpu_medians["total without decoding"]
                                         - cpu_medians["publish"]
                                         + cpu_medians["publish, all outputs"])
    return {"preset": preset, "input": cfg.image_size, "sets": sets,
            "jpeg_kb": round(statistics.mean(len(d) for d in jpegs) / 1024),
            "jpeg_hw": (height, width), "model_ms_one_step": step_ms,
            "occupied_voxels": int((result.grid != cfg.labels.free_label).sum()),
            "boxes": len(result.boxes), "median_ms": medians, "cpu_median_ms": cpu_medians,
            "overlap": overlap, "load": os.getloadavg()[0]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="odg_cpu,odg_t",
                        help="comma-separated presets (default: odg_cpu,odg_t)")
    parser.add_argument("--sets", type=int, default=30, help="camera sets timed (median)")
    parser.add_argument("--checkpoint", default=None, help="weights (default: random)")
    parser.add_argument("--images", default=None,
                        help="glob of six JPEGs of one size (default: synthetic 1600x900)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--occupied", type=int, default=40000,
                        help="occupied voxels at least in the replayed grid (default 40000, "
                             "the shipped odg_cpu checkpoint's on these images)")
    parser.add_argument("--boxes", type=int, default=30, help="valid boxes replayed")
    parser.add_argument("--model-ms", type=float, default=0.0,
                        help="also time sets per second with the model as a sleep of this "
                             "long, decoding serial or overlapped (default: not timed)")
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
            r = measure(preset.strip(), jpegs, args.sets, args.checkpoint, publish_with,
                        args.occupied, args.boxes, args.model_ms)
            if ros is not None:
                ros[0].destroy_node()
                ros[1].shutdown()
                ros = None
            print(f"{r['preset']}: input {r['input'][0]}x{r['input'][1]}, six "
                  f"{r['jpeg_hw'][0]}x{r['jpeg_hw'][1]} JPEGs (~{r['jpeg_kb']} kB each), "
                  f"{r['occupied_voxels']} occupied voxels, {r['boxes']} boxes; one model "
                  f"step {r['model_ms_one_step']:.0f} ms (not included); median of "
                  f"{r['sets']} sets:")
            print(f"  wall time per stage (load average {r['load']:.1f} on "
                  f"{os.cpu_count()} cores):")
            for stage, ms in r["median_ms"].items():
                print(f"    {stage:<28}{ms:8.2f} ms")
            print("  CPU time of the calling thread:")
            for stage, ms in r["cpu_median_ms"].items():
                print(f"    {stage:<28}{ms:8.2f} ms")
            if r["overlap"]:
                o = r["overlap"]
                print(f"  model as a {args.model_ms:g} ms sleep, ms per set: decoding in the "
                      f"worker {o['serial']:.1f}, ahead of it {o['overlapped']:.1f} "
                      f"(ratio {o['serial'] / o['overlapped']:.2f})")
    finally:
        if ros is not None:
            ros[0].destroy_node()
            ros[1].shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
