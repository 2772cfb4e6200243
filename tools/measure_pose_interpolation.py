"""How far off the node's interpolated ego poses are when only sparse poses are available
(nuScenes converters publish TF at 2 Hz keyframes), against the synthetic world's true
poses at every camera stamp.

    python -m tools.measure_pose_interpolation --json docs/results/pose_interpolation.json \
        --plot docs/results/pose_interpolation.png
    python -m tools.measure_pose_interpolation --scenes 2 --roads city --gaps 0.5 1.0

The worlds are ``odg synth``'s (same --seed, scene index and --roads: the ego drives the
city's turns, stops and starts, or an open road). For each gap g, poses are taken every g s
(the first at the first LiDAR keyframe, as nuScenes keyframes are) and fed to the node's
PoseBuffer (interpolation bound g, the node's motion checks); every camera of every camera
set inside that span is then looked up as the node does. Errors against the true pose:

* translation (m) and rotation (deg) of the ego pose at each camera stamp;
* camera in set (px): a point 20 m down each camera's optical axis, placed with the true
  camera-to-reference-ego transform, projected with the interpolated one (the camera
  placement within a set, the only part of the current frame's geometry that depends on
  poses), at nuScenes' 1600 x 900 px;
* history warp (voxels): the ego motion between a set and the one 0.5 s earlier (what
  warps the history frames), as a displacement of points 40 m away (the grid's edge), in
  0.4 m voxels.

Prints p50 / p95 / max per gap and road kind (pooled over cameras and scenes), over all
stamps and over the stamps in turns (true yaw rate above 3 deg/s, where linear interpolation
errs most), and the number of pose samples the motion checks rejected (0 expected); --json
writes them, --plot draws them. The synthetic ego drives straight at constant speed much of
the time (interpolation is exact there), and takes some turns without slowing down (up to
2 g: harder than a real car), so "turns" is a pessimistic case.
"""
from __future__ import annotations

import argparse
import itertools
import json
import math

import numpy as np
from tqdm import tqdm

from odg_ros.data.synth import sensor_rig
from odg_ros.data.synth.city import SceneKind
from odg_ros.data.synth.generate import camera_time, keyframe_time, scene_world
from odg_ros.geometry import invert_transform
from odg_ros.online.errors import BadInput
from odg_ros.online.poses import PoseBuffer

VOXEL = 0.4                 # m
HISTORY_STEP = 6            # camera sets between a frame and its history frame (0.5 s)
GRID_EDGE = 40.0            # m
POINT_DEPTH = 20.0          # m down a camera's optical axis
TURNING = math.radians(3.0)  # rad/s of yaw rate: "in a turn"
METRICS = ("translation_m", "rotation_deg", "camera_px", "history_voxels")
LINEAR_BELOW = {"translation_m": 0.01, "rotation_deg": 0.1, "camera_px": 0.1,
                "history_voxels": 0.01}
SUBSETS = ("all", "turns")


def rotation_deg(R_a, R_b) -> float:
    cos = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def project(K, T_cam_from_ego, point_ego) -> np.ndarray:
    p = T_cam_from_ego[:3, :3] @ point_ego + T_cam_from_ego[:3, 3]
    uvw = K @ p
    return uvw[:2] / uvw[2]


def yaw_rate(world, t: float, dt: float = 0.05) -> float:
    """|true yaw rate| at ``t``, rad/s."""
    a, b = world.ego_pose(t - dt), world.ego_pose(t + dt)
    return math.radians(rotation_deg(a[:3, :3], b[:3, :3])) / (2 * dt)


def measure_world(world, gap: float, cameras) -> tuple[dict, int]:
    """({subset: {metric: values}}, samples rejected by the motion checks) of one world at
    one gap."""
    buffer = PoseBuffer(max_interpolation_gap=gap * 1.001, max_speed=70.0,
                        max_acceleration=30.0)
    t, rejected = keyframe_time(0), 0
    while t <= world.duration:
        try:
            buffer.add(t, world.ego_pose(t))
        except BadInput:
            rejected += 1
        t += gap
    first, last = buffer.span
    values = {subset: {m: [] for m in METRICS} for subset in SUBSETS}

    def add(metric, value, turning):
        values["all"][metric].append(value)
        if turning:
            values["turns"][metric].append(value)

    reference = "CAM_FRONT"
    sets = []                       # the camera sets inside the span of the poses
    for m in itertools.count():
        stamps = {c.name: camera_time(m, c.name) for c in cameras}
        if max(stamps.values()) > last:
            break
        if min(stamps.values()) >= first:
            sets.append((m, stamps))
    interpolated, true, turning = {}, {}, {}
    for m, stamps in sets:
        turning[m] = yaw_rate(world, stamps[reference]) > TURNING
        for name, stamp in stamps.items():
            P_i, P_t = buffer.lookup(stamp), world.ego_pose(stamp)
            interpolated[m, name], true[m, name] = P_i, P_t
            add("translation_m", float(np.linalg.norm(P_i[:3, 3] - P_t[:3, 3])), turning[m])
            add("rotation_deg", rotation_deg(P_i[:3, :3], P_t[:3, :3]), turning[m])
    for m, stamps in sets:
        ref_i, ref_t = interpolated[m, reference], true[m, reference]
        for cam in cameras:
            cam_from_ego = invert_transform(cam.T_ego_from_cam)
            # camera n relative to the reference ego: inv(sensor2ego) inv(P(t_n)) P(t_ref)
            T_i = cam_from_ego @ invert_transform(interpolated[m, cam.name]) @ ref_i
            T_t = cam_from_ego @ invert_transform(true[m, cam.name]) @ ref_t
            point = invert_transform(T_t) @ np.array([0.0, 0.0, POINT_DEPTH, 1.0])
            add("camera_px", float(np.linalg.norm(
                project(cam.intrinsics, T_i, point[:3]) - project(cam.intrinsics, T_t,
                                                                  point[:3]))), turning[m])
    headings = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    ring = np.stack([GRID_EDGE * np.cos(headings), GRID_EDGE * np.sin(headings),
                     np.zeros(16), np.ones(16)])
    indices = {m for m, _ in sets}
    for m, _ in sets:
        if m - HISTORY_STEP not in indices:
            continue
        warps = [invert_transform(P[m, reference]) @ P[m - HISTORY_STEP, reference]
                 for P in (interpolated, true)]
        moved = np.linalg.norm((warps[0] @ ring - warps[1] @ ring)[:3], axis=0)
        add("history_voxels", float(moved.max() / VOXEL),
            turning[m] or turning[m - HISTORY_STEP])
    return values, rejected


def summarize(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, np.float64)
    return {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)),
            "max": float(a.max()), "n": int(a.size)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=16, help="worlds per road kind")
    parser.add_argument("--seconds", type=float, default=20.0, help="length of each world")
    parser.add_argument("--seed", type=int, default=0, help="odg synth's --seed")
    parser.add_argument("--roads", nargs="+", default=["city", "open-road"],
                        choices=["city", "open-road"])
    parser.add_argument("--gaps", type=float, nargs="+", default=[0.02, 0.5, 0.55, 0.75, 1.0],
                        help="seconds between the poses given (0.02: 50 Hz odometry)")
    parser.add_argument("--json", help="write the summary here")
    parser.add_argument("--plot", help="draw p50 / p95 per gap into this PNG")
    args = parser.parse_args(argv)
    cameras = sensor_rig.cameras()
    results, rejected = {}, {}
    jobs = [(roads, index) for roads in args.roads for index in range(args.scenes)]
    pooled = {(roads, gap, subset): {m: [] for m in METRICS} for roads in args.roads
              for gap in args.gaps for subset in SUBSETS}
    for roads, index in tqdm(jobs, desc="worlds", unit="world"):
        world = scene_world(args.seed, index, args.seconds, SceneKind(roads=roads))
        for gap in args.gaps:
            values, n = measure_world(world, gap, cameras)
            rejected[roads, gap] = rejected.get((roads, gap), 0) + n
            for subset in SUBSETS:
                for m in METRICS:
                    pooled[roads, gap, subset][m] += values[subset][m]
    print(f"{'roads':9} {'gap s':>6} {'stamps':>6} {'n':>6} "
          + " ".join(f"{m + ' p50/p95/max':>30}" for m in METRICS) + "  rejected")
    for (roads, gap, subset), values in pooled.items():
        if not values["translation_m"]:
            continue
        summary = {m: summarize(v) for m, v in values.items()}
        results[f"{roads} {gap:g} {subset}"] = dict(summary, rejected=rejected[roads, gap])
        print(f"{roads:9} {gap:6.2f} {subset:>6} {summary['translation_m']['n']:6d} "
              + " ".join(f"{s['p50']:9.3g} {s['p95']:9.3g} {s['max']:9.3g}"
                         for s in summary.values()) + f"  {rejected[roads, gap]}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"scenes": args.scenes, "seconds": args.seconds, "seed": args.seed,
                       "results": results}, f, indent=1)
    if args.plot:
        plot(results, args, args.plot)
    return 0


def plot(results: dict, args, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    labels = {"translation_m": "ego translation (m)", "rotation_deg": "ego rotation (deg)",
              "camera_px": "camera in set (px, 1600 x 900)",
              "history_voxels": "history warp at 40 m (voxels)"}
    figure, axes = plt.subplots(1, len(METRICS), figsize=(4 * len(METRICS), 3.4))
    for ax, metric in zip(axes, METRICS):
        for roads, style in zip(args.roads, ("-", "--")):
            for subset, q, marker in (("all", "p95", "o"), ("turns", "p95", "^"),
                                      ("turns", "max", "x")):
                key = f"{roads} {{:g}} {subset}"
                if key.format(args.gaps[0]) not in results:
                    continue
                ys = [results[key.format(g)][metric][q] for g in args.gaps]
                ax.plot(args.gaps, ys, style, marker=marker, label=f"{roads}, {subset} {q}")
        ax.set_yscale("symlog", linthresh=LINEAR_BELOW[metric])   # 0 on straight roads
        ax.set_xlabel("seconds between poses")
        ax.set_title(labels[metric], fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    figure.suptitle(f"Interpolated against true ego poses: {args.scenes} synthetic worlds of "
                    f"{args.seconds:g} s per road kind (seed {args.seed})", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
