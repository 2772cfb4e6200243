"""Time RayIoU's ray casting per sample against an earlier revision of the caster, in one
process, interleaved, medians.

    python -m tools.bench_raycast [--against main] [--repeats 5]

World: a driving-like 200 x 200 x 16 grid (ground, 25 cars, walls); prediction = GT shifted one
voxel along x + 3 % spurious cars; 8 origins x 14,040 LiDAR rays, prediction and GT traversed
together (what ``RayIoU.add`` casts per keyframe).
"""
import argparse
import inspect
import time

import numpy as np

from testing.helpers import driving_scene
from tools.revision import module_at

from odg_ros.metrics.raycast import cast_rays, lidar_ray_directions, rays_in_voxel_units  # noqa

FREE, SHAPE = 17, (200, 200, 16)
GRID_MIN = np.array([-40.0, -40.0, -1.0])


def world(rng):
    g = driving_scene(rng, SHAPE, FREE)
    pred = np.full_like(g, FREE)
    pred[1:] = g[:-1]
    pred[rng.random(SHAPE) < 0.03] = 4
    return (pred != FREE).astype(np.uint8) | ((g != FREE).astype(np.uint8) << 1)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", default="main")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    bits = world(np.random.default_rng(11))
    origins = np.array([[0.985793, 0.0, 1.84019]]
                       + [[x, 0.3 * x, 1.84] for x in (-30, -20, -10, 5, 15, 25, 35)])
    dirs = lidar_ray_directions().astype(np.float64)
    o = np.repeat(origins, len(dirs), 0)
    d = np.tile(dirs, (len(origins), 1))
    start, end = rays_in_voxel_units(o, d, GRID_MIN, 0.4)
    before = module_at(args.against, "odg_ros/metrics/raycast.py")
    if "directions" in inspect.signature(before.cast_rays).parameters:   # (origins, unit dirs)
        old_args = ((o - GRID_MIN) / 0.4, d / np.linalg.norm(d, axis=1, keepdims=True))
    else:
        old_args = (start, end)
    t_old, t_new = [], []
    for _ in range(args.repeats):
        t = time.perf_counter()
        before.cast_rays(bits, *old_args, num_bits=2)
        t_old.append(time.perf_counter() - t)
        t = time.perf_counter()
        cast_rays(bits, start, end, num_bits=2)
        t_new.append(time.perf_counter() - t)
    print(f"{args.against}: {np.median(t_old):.3f} s, this tree: {np.median(t_new):.3f} s per "
          f"sample (medians of {args.repeats}); ratio {np.median(t_new) / np.median(t_old):.2f}")


if __name__ == "__main__":
    main()
